"""The layering of ``appliance/`` holds: no module imports a layer above its own.

The rules are data (below), taken from ``../shared/design/ARCHITECTURE.md`` and ``docs/architecture.md``. The
import graph is read with :mod:`ast` from every module, including imports inside functions and under
``TYPE_CHECKING``, so a lazy import cannot hide an edge.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "appliance"

LAYERS: dict[str, tuple[str, ...]] = {
    # layer: the module prefixes that belong to it (longest prefix wins)
    "cli": ("appliance.cli", "appliance.__main__", "appliance.commands", "appliance.fleet"),
    "service": ("appliance.service",),
    "scan": ("appliance.scan", "appliance.replay", "appliance.procedures"),
    "output": ("appliance.output",),
    "fakes": ("appliance.fakes",),
    "hardware": ("appliance.hardware",),
    "firmware": ("appliance.firmware",),
    "calibration": ("appliance.calibration",),
    "sim": ("appliance.sim",),
    "reconstruct": ("appliance.reconstruct",),
    "patterns": ("appliance.patterns",),
    "geometry": ("appliance.geometry",),
    "config": ("appliance.config",),
    "base": ("appliance", "appliance.errors"),  # the package itself (__version__) and the exception hierarchy
}

_ORDER = ("cli", "service", "scan", "output", "hardware", "calibration", "sim", "reconstruct", "patterns",
          "geometry", "config", "base")


def _above(layer: str) -> set[str]:
    return set(_ORDER[: _ORDER.index(layer)])


FORBIDDEN: dict[str, set[str]] = {
    layer: _above(layer) | ({"fakes"} if layer != "cli" else set()) for layer in _ORDER
}
# The test doubles (fake GigE camera, fake DLPC350) sit beside the product: they drive hardware/ backends
# and may use everything below; nothing in the product imports them (only the command line, for
# `scan3d simulate-camera`).
FORBIDDEN["fakes"] = {"cli", "service", "scan", "output"}
# The trigger controller's firmware runs on the board: it shares its protocol module with the host and
# imports nothing else of the appliance.
FORBIDDEN["firmware"] = set(LAYERS) - {"firmware"}
# reconstruct/ is pure: it takes plain parameter objects, not the pydantic configuration.
FORBIDDEN["reconstruct"] |= {"config"}
FORBIDDEN["config"] = set(LAYERS) - {"config", "base"}
FORBIDDEN["base"] = set(LAYERS) - {"base"}
for _layer in ("calibration", "sim", "reconstruct", "patterns", "geometry"):
    FORBIDDEN[_layer] |= {"firmware"}

ONLY_IMPORTED_BY: dict[str, set[str]] = {
    # reading configuration files is for the command line, the service and the procedures they run
    "appliance.config.loader": {"cli", "service", "scan", "config"},
}

EVENT_LOOP_STARTERS = ("asyncio.run", "run_until_complete")
EVENT_LOOP_OWNERS = ("appliance/service/", "appliance/cli.py")

# Inside service/, one part (the daemon) owns the rig, the scanner and the other parts; every other part gets the
# status board and a small protocol of what it may call (as faces.ServiceView does), never the daemon itself.
DAEMON_MODULE = "appliance.service.daemon"
DAEMON_IMPORTERS_ALLOWED = {
    "appliance.cli",  # `scan3d run` starts the daemon
    "appliance.service.bench",  # the service bench runs a whole daemon and measures it; it is no part of one
}
# Service parts that still take the whole daemon (none since issue 26 item 4: each has its protocol in
# appliance/service/parts.py; an entry here must still import the daemon, the stale check keeps that so).
KNOWN_DAEMON_IMPORTERS: set[str] = set()

# Known, to be moved (each in a file another change owns; remove the entry when it is fixed, the test
# then keeps it fixed). (importer, imported module)
KNOWN_EDGES: set[tuple[str, str]] = set()
# Known event-loop starters outside service/ and cli.py: (file, line text)
KNOWN_LOOPS: set[str] = set()


@dataclass(frozen=True)
class Edge:
    importer: str
    imported: str
    line: int


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _module_file(name: str) -> Path | None:
    rel = Path(*name.split("."))
    for cand in (PACKAGE.parent / rel.with_suffix(".py"), PACKAGE.parent / rel / "__init__.py"):
        if cand.exists():
            return cand
    return None


def _reexports(package: str) -> dict[str, str]:
    """Names a package's ``__init__`` imports from its submodules: name -> module."""
    init = _module_file(package)
    if init is None or init.name != "__init__.py":
        return {}
    out = {}
    for node in ast.walk(ast.parse(init.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                out[alias.asname or alias.name] = node.module
    return out


def imports_of(path: Path) -> list[Edge]:
    """Every import of an ``appliance`` module in ``path``, resolved to the module it reaches."""
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    edges = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            edges += [Edge(me, a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "appliance"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "appliance":
                continue
            reexports = _reexports(target)
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if _module_file(sub) is not None:
                    edges.append(Edge(me, sub, node.lineno))
                else:
                    edges.append(Edge(me, reexports.get(alias.name, target), node.lineno))
    return edges


def layer_of(module: str) -> str:
    best, best_len = "", -1
    for layer, prefixes in LAYERS.items():
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = layer, len(p)
    if not best:
        raise AssertionError(f"{module}: in no layer; add it to LAYERS in tests/test_layering.py")
    return best


def all_edges() -> list[Edge]:
    return [e for p in sorted(PACKAGE.rglob("*.py")) for e in imports_of(p)]


def violations(edges: list[Edge]) -> list[str]:
    """The forbidden edges, one line each: importer:line (layer) -> imported (layer)."""
    bad = []
    for e in edges:
        src, dst = layer_of(e.importer), layer_of(e.imported)
        rule = None
        if dst in FORBIDDEN[src]:
            rule = f"{src} must not import {dst}"
        for module, allowed in ONLY_IMPORTED_BY.items():
            if (e.imported == module or e.imported.startswith(module + ".")) and src not in allowed:
                rule = f"{module} is only for {sorted(allowed)}"
        if rule is not None and (e.importer, e.imported) not in KNOWN_EDGES:
            bad.append(f"{e.importer}:{e.line} -> {e.imported}: {rule}")
    return bad


def loop_starters() -> list[str]:
    """``asyncio.run(...)`` / ``loop.run_until_complete(...)`` calls (and references) outside the owners."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).as_posix()
        if rel.startswith(EVENT_LOOP_OWNERS) or rel in KNOWN_LOOPS:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Attribute) and (
                node.attr == "run_until_complete"
                or (node.attr == "run" and isinstance(node.value, ast.Name) and node.value.id == "asyncio")
            ):
                found.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
            elif isinstance(node, ast.ImportFrom) and node.module == "asyncio":
                found += [f"{rel}:{node.lineno}: from asyncio import run" for a in node.names if a.name == "run"]
    return found


def test_every_module_is_in_a_layer() -> None:
    for path in PACKAGE.rglob("*.py"):
        layer_of(module_name(path))


def test_no_import_against_the_layering() -> None:
    bad = violations(all_edges())
    assert not bad, "imports against the layering (docs/architecture.md):\n" + "\n".join(bad)


def test_known_exceptions_are_still_needed() -> None:
    """An entry of the allow-lists that no longer matches anything is removed, so it cannot hide a new edge."""
    edges = {(e.importer, e.imported) for e in all_edges()}
    assert KNOWN_EDGES <= edges, f"stale KNOWN_EDGES entries: {sorted(KNOWN_EDGES - edges)}"
    for rel in KNOWN_LOOPS:
        text = (PACKAGE.parent / rel).read_text()
        assert any(s in text for s in EVENT_LOOP_STARTERS), f"stale KNOWN_LOOPS entry: {rel}"


def test_event_loops_start_only_in_the_service_and_the_command_line() -> None:
    found = loop_starters()
    assert not found, "event loop started outside service/ and cli.py:\n" + "\n".join(found)


# --- the checker itself catches what it is for ---------------------------------------------------------


@pytest.mark.parametrize(
    ("importer", "imported", "caught"),
    [
        ("appliance.calibration.rig", "appliance.hardware.base", True),
        ("appliance.calibration.rig", "appliance.scan", True),
        ("appliance.reconstruct.decode", "appliance.config.schema", True),
        ("appliance.hardware.aravis", "appliance.fakes.gige", True),
        ("appliance.fakes.gige", "appliance.scan", True),
        ("appliance.fakes.gige", "appliance.config.loader", True),
        ("appliance.geometry.camera", "appliance.patterns.sequence", True),
        ("appliance.firmware.controller", "appliance.errors", True),
        ("appliance.commands", "appliance.fakes.gige", False),
        ("appliance.hardware.serial", "appliance.firmware.protocol", False),
        ("appliance.fakes.gige", "appliance.hardware.aravis", False),
        ("appliance.scan", "appliance.reconstruct.pipeline", False),
    ],
)
def test_checker_rules(importer: str, imported: str, caught: bool) -> None:
    assert bool(violations([Edge(importer, imported, 1)])) is caught


def test_checker_reads_function_level_and_relative_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = tmp_path / "appliance"
    (pkg / "geometry").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "scan.py").write_text("")
    (pkg / "geometry" / "__init__.py").write_text("")
    (pkg / "geometry" / "camera.py").write_text(
        "def f():\n    from appliance import scan\n    from .. import scan as s\n    import appliance.scan\n"
    )
    (pkg / "geometry" / "loop.py").write_text("import asyncio\n\ndef g():\n    asyncio.run(None)\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    edges = imports_of(pkg / "geometry" / "camera.py")
    assert [(e.imported, e.line) for e in edges] == [("appliance.scan", 2), ("appliance.scan", 3),
                                                      ("appliance.scan", 4)]
    assert len(violations(edges)) == 3
    assert loop_starters() == ["appliance/geometry/loop.py:4: asyncio.run"]


def daemon_importers(edges: list[Edge]) -> list[str]:
    """Modules other than the daemon that import it (``Service`` or the module), one line each."""
    return sorted({f"{e.importer}:{e.line}" for e in edges
                   if (e.imported == DAEMON_MODULE or e.imported.startswith(DAEMON_MODULE + "."))
                   and e.importer != DAEMON_MODULE and e.importer not in DAEMON_IMPORTERS_ALLOWED})  # fmt: skip


def test_no_service_part_takes_the_whole_daemon() -> None:
    """A service part gets the status board and a small protocol, never ``daemon.Service`` (TYPE_CHECKING too)."""
    found = daemon_importers(all_edges())
    new = [f for f in found if f.split(":")[0] not in KNOWN_DAEMON_IMPORTERS]
    assert not new, "service modules importing the daemon (give them a protocol, as faces.ServiceView):\n" + \
        "\n".join(new)
    stale = KNOWN_DAEMON_IMPORTERS - {f.split(":")[0] for f in found}
    assert not stale, f"no longer import the daemon, remove from KNOWN_DAEMON_IMPORTERS: {sorted(stale)}"


SERVICE_DIR = PACKAGE / "service"
SHARED_FIELDS = {"board"}  # the status board is every part's to write (each its own fields of it)


def reaches_into_others(source: str, path: str = "<test>") -> list[str]:
    """In one service module: a private attribute of anything but ``self``/``cls`` (``svc._make_scanner``), and an
    assignment to a field of another object held by a part (``self.jobs.abort_reason = ...``), one line each."""
    found = []
    for node in ast.walk(ast.parse(source, path)):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                found.append(f"{path}:{node.lineno}: {ast.unparse(node)} (a private attribute of another object)")
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])  # fmt: skip
        for target in targets:
            for t in ast.walk(target):
                if (isinstance(t, ast.Attribute) and isinstance(t.value, ast.Attribute)
                        and isinstance(t.value.value, ast.Name) and t.value.value.id == "self"
                        and t.value.attr not in SHARED_FIELDS):  # fmt: skip
                    found.append(f"{path}:{node.lineno}: {ast.unparse(t)} = ... (another part's field: call it)")
    return found


def test_no_service_part_reaches_into_another() -> None:
    """A part changes another only by calling it, and calls nothing private of it (the daemon included)."""
    found = [f for p in sorted(SERVICE_DIR.glob("*.py"))
             for f in reaches_into_others(p.read_text(), p.relative_to(PACKAGE.parent).as_posix())]  # fmt: skip
    assert not found, "service parts reaching into each other:\n" + "\n".join(found)


@pytest.mark.parametrize(
    ("source", "caught"),
    [
        ("def f(self):\n    self.svc._make_scanner(1)\n", True),
        ("def f(self):\n    self.jobs.abort_reason = 'x'\n", True),
        ("def f(self):\n    self.hardware.changed.set()\n", False),  # a call, not a write
        ("def f(self):\n    self.board.share = {}\n    self._lamps = None\n", False),
    ],
)
def test_reach_checker(source: str, caught: bool) -> None:
    assert bool(reaches_into_others(source)) is caught


@pytest.mark.parametrize(
    ("importer", "imported", "caught"),
    [
        ("appliance.service.mqtt", "appliance.service.daemon", True),
        ("appliance.service.faces", "appliance.service.daemon.Service", True),
        ("appliance.service.jobs", "appliance.service.daemon", True),
        ("appliance.service.rig", "appliance.service.daemon.Service", True),
        ("appliance.cli", "appliance.service.daemon", False),
        ("appliance.service.daemon", "appliance.service.jobs", False),
    ],
)
def test_daemon_rule_checker(importer: str, imported: str, caught: bool) -> None:
    found = [f for f in daemon_importers([Edge(importer, imported, 1)])
             if f.split(":")[0] not in KNOWN_DAEMON_IMPORTERS]  # fmt: skip
    assert bool(found) is caught


# --- private kernels stay in their package ---------------------------------------------------------------


def private_kernel_imports(edges: list[Edge]) -> list[str]:
    """Imports of another package's private numba kernels (``pkg._*kernels``), one line each.

    A package's public functions check their inputs and call its kernels; a module elsewhere calls those functions
    (e.g. ``reconstruct.decode.kernels_compiled``, not ``_decode_kernels.decode_stack``). Kernel modules may import
    each other's kernels: numba inlines a jitted helper only through an import.
    """
    found = []
    for e in edges:
        package, _, leaf = e.imported.rpartition(".")
        if not (leaf.startswith("_") and leaf.endswith("kernels")):
            continue
        importer_leaf = e.importer.rpartition(".")[2]
        a_kernel_module = importer_leaf.startswith("_") and importer_leaf.endswith("kernels")
        if e.importer.startswith(package + ".") or a_kernel_module:
            continue
        found.append(f"{e.importer}:{e.line} -> {e.imported}")
    return sorted(found)


def test_no_private_kernel_is_imported_across_packages() -> None:
    found = private_kernel_imports(all_edges())
    assert not found, "private kernels imported from outside their package (call its public function):\n" + \
        "\n".join(found)


@pytest.mark.parametrize(
    ("importer", "imported", "caught"),
    [
        ("appliance.commands", "appliance.reconstruct._decode_kernels", True),
        ("appliance.scan", "appliance.geometry._distortion_kernels", True),
        ("appliance.reconstruct.decode_batch", "appliance.reconstruct._decode_kernels", False),
        ("appliance.reconstruct._stereo_kernels", "appliance.geometry._distortion_kernels", False),
        ("appliance.commands", "appliance.reconstruct.decode", False),
    ],
)
def test_private_kernel_rule_checker(importer: str, imported: str, caught: bool) -> None:
    assert bool(private_kernel_imports([Edge(importer, imported, 1)])) is caught


# --- numba kernels: a fastmath kernel's helpers set fastmath themselves -----------------------------------------


def _njit_functions() -> dict[str, tuple[str, dict[str, str], set[str]]]:
    """Every module-level ``@njit(...)`` function of the package: its file, decorator options and called names."""
    found: dict[str, tuple[str, dict[str, str], set[str]]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if not isinstance(node, ast.FunctionDef):
                continue
            for deco in node.decorator_list:
                if isinstance(deco, ast.Call) and isinstance(deco.func, ast.Name) and deco.func.id == "njit":
                    opts = {k.arg: ast.unparse(k.value) for k in deco.keywords if k.arg}
                    calls = {c.func.id if isinstance(c.func, ast.Name) else c.func.attr
                             for c in ast.walk(node) if isinstance(c, ast.Call)
                             and isinstance(c.func, (ast.Name, ast.Attribute))}  # fmt: skip
                    found[node.name] = (str(path.relative_to(PACKAGE.parent)), opts, calls)
    return found


def test_helpers_of_fastmath_kernels_set_fastmath_themselves() -> None:
    """numba compiles a helper that does not set ``fastmath`` with its first caller's flags and keeps that version
    for every caller (``inherit_if_not_set``): a helper shared by a fastmath kernel and an exact one then rounds
    by whichever compiled first (seen: a code on the lowest cell edge dropped after ``cell_match`` compiled
    ``_row_cells``). Helpers inlined at numba level (``inline='always'``) are part of each caller and exempt."""
    funcs = _njit_functions()
    fast = [name for name, (_, opts, _) in funcs.items() if opts.get("fastmath", "False") != "False"]
    assert "cell_match" in fast  # the rule reads the kernels it is about
    bad = []
    for kernel in fast:
        todo, seen = [kernel], {kernel}
        while todo:
            for callee in funcs[todo.pop()][2]:
                if callee in funcs and callee not in seen:
                    seen.add(callee)
                    todo.append(callee)
                    path, opts, _ = funcs[callee]
                    if "fastmath" not in opts and opts.get("inline") != "'always'":
                        bad.append(f"{path}: {callee} (called by {kernel})")
    assert bad == [], f"helpers of fastmath kernels that inherit their caller's flags: {bad}"
