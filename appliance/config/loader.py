"""Loading the YAML configuration with errors that name file, line, key path, value and rule."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import stat
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from appliance.config.schema import AppConfig
from appliance.config.strict import STRICT_TYPE
from appliance.config.yamlfile import DuplicateKeyError, parse_yaml, read_bytes_file, yaml_problem
from appliance.errors import ConfigError

MAX_CONFIG_BYTES = 32 * 1024 * 1024
"""Largest configuration file read (bytes); an inline mesh of ~8 MB is well within it."""

MAX_PROBLEMS = 20
"""Problems listed one per line; the rest are counted."""

LIFT_MIN_CHARS = 64 * 1024
"""A flow list of plain numbers at least this long (characters) is read by the JSON decoder (an inline mesh)."""

INLINE_MESH_NOTE_BYTES = 1024 * 1024
INLINE_MESH_NOTE_VERTICES = 20_000
"""A configuration over ~1 MB with an inline mesh of more vertices than this gets a log line: use a mesh file."""

_LIST_START = re.compile(r"(?:^[ \t]*(?:-[ \t]+)+|:[ \t]+|[,\[{][ \t]*)\[", re.M)
_NUMERIC_LIST = re.compile(r"[0-9.\-\s\[\],]*")
_AFTER_LIST = re.compile(r"[ \t]*(?:$|#|,|\]|\})", re.M)
_JSON = json.JSONDecoder()
log = logging.getLogger(__name__)


def _keys_of(node: yaml.MappingNode, index: dict[int, dict[str, tuple[yaml.Node, yaml.Node]]],
             ) -> dict[str, tuple[yaml.Node, yaml.Node]]:
    """The scalar keys of a mapping node (built once per node, so locating N errors stays linear)."""
    keys = index.get(id(node))
    if keys is None:
        keys = {}
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode):
                keys.setdefault(k.value, (k, v))
        index[id(node)] = keys
    return keys


def _node_at(root: yaml.Node | None, loc: tuple[int | str, ...],
             index: dict[int, dict[str, tuple[yaml.Node, yaml.Node]]] | None = None) -> yaml.Node | None:
    """The deepest YAML node along ``loc`` (pydantic's error location)."""
    index = {} if index is None else index
    node = root
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            pair = _keys_of(node, index).get(str(key))
            if pair is None:
                return node
            node = pair[1] if not _is_last(loc, key) else pair[0]
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            return node
    return node


def _is_last(loc: tuple[int | str, ...], key: int | str) -> bool:
    return bool(loc) and loc[-1] == key


def _lookup(doc: Any, loc: tuple[int | str, ...]) -> tuple[bool, Any]:
    cur = doc
    for key in loc:
        if isinstance(cur, dict) and key in cur:
            cur = cur[key]
        elif isinstance(cur, list) and isinstance(key, int) and key < len(cur):
            cur = cur[key]
        else:
            return False, None
    return True, cur


def _clean_loc(loc: tuple[int | str, ...], doc: Any) -> tuple[int | str, ...]:
    """Drop pydantic's union-tag elements (e.g. 'sim' in cameras.cam0.sim.exposure_us)."""
    out: list[int | str] = []
    cur = doc
    for key in loc:
        if isinstance(cur, dict) and key in cur:
            cur = cur[key]
            out.append(key)
        elif isinstance(cur, list) and isinstance(key, int) and key < len(cur):
            cur = cur[key]
            out.append(key)
        elif isinstance(cur, dict) and isinstance(key, str) and cur.get("type") == key:
            continue  # discriminator tag
        elif isinstance(key, str) and ("[" in key or key.startswith("function-")):
            continue
        else:
            out.append(key)
            cur = None
    return tuple(out)


def format_validation_error(exc: ValidationError, source: str, doc: Any, root: yaml.Node | None) -> str:
    """One line per problem: ``file:line: key.path = value: rule``; past :data:`MAX_PROBLEMS`, a count."""
    lines = []
    errors = exc.errors(include_url=False)
    # pydantic follows a list item's error with "at least N items" on the list (it counts the valid ones):
    # the item's line says it all
    items_at = {tuple(e["loc"][:-1]) for e in errors if e["loc"] and isinstance(e["loc"][-1], int)}
    errors = [e for e in errors if not (e["type"] == "too_short" and tuple(e["loc"]) in items_at)]
    index: dict[int, dict[str, tuple[yaml.Node, yaml.Node]]] = {}
    for err in errors[:MAX_PROBLEMS]:
        loc = _clean_loc(tuple(err["loc"]), doc)
        rule = err["msg"]
        if err["type"] == STRICT_TYPE:  # a model-level check: its context names the field
            ctx = err.get("ctx") or {}
            loc = (*loc, str(ctx.get("field", "?")), *(int(i) for i in ctx.get("items", ())))
            rule = str(ctx.get("rule", rule))
        elif err["type"] == "extra_forbidden":
            rule = "unknown key (check its spelling against config/appliance.yaml)"
        elif err["type"] == "missing":
            rule = "required key is missing"
        elif rule.startswith("Value error, "):
            rule = rule[len("Value error, "):]
        path = ".".join(str(p) for p in loc) or "(top level)"
        node = _node_at(root, loc, index)
        line = f"{node.start_mark.line + 1}" if node is not None else "?"
        found, value = _lookup(doc, loc)
        shown = f" = {_short(value)}" if found and not isinstance(value, dict | list) else ""
        lines.append(f"{source}:{line}: {path}{shown}: {rule}")
    if len(errors) > MAX_PROBLEMS:
        unknown = sum(e["type"] == "extra_forbidden" for e in errors)
        lines.append(f"{source}: ... and {len(errors) - MAX_PROBLEMS} more problems ({unknown} unknown keys in all); "
                     "fix these first (is this the right file?)")
    return "\n".join(lines)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def parse_config(text: str, source: str = "<config>", base_dir: Path | None = None) -> AppConfig:
    """Validate configuration text.

    Parameters
    ----------
    text : str
        YAML text.
    source : str
        The file name used in messages.
    base_dir : Path, optional
        Relative mesh paths are resolved against it.

    Raises
    ------
    ConfigError
        With one ``file:line: key.path = value: rule`` line per problem.
    """
    if "\x00" in text:
        raise ConfigError(f"{source}: not a YAML mapping (binary data: a NUL character at offset "
                          f"{text.index(chr(0))}); restore the file from config/appliance.yaml or a backup")
    try:
        doc, root, lifted = _parse_fast(text)
    except DuplicateKeyError as exc:
        where, problem = yaml_problem(exc, source)
        raise ConfigError(f"{where}: {problem}") from exc
    except yaml.MarkedYAMLError as exc:
        where, problem = yaml_problem(exc, source)
        raise ConfigError(f"{where}: not valid YAML: {problem}; check indentation and quoting") from exc
    except yaml.YAMLError as exc:  # e.g. a reader error: a character YAML does not allow
        problem = " ".join(str(exc).split())
        raise ConfigError(f"{source}: not valid YAML: {problem}; remove the character or restore the file") from exc
    except RecursionError as exc:
        raise ConfigError(f"{source}: not valid YAML: nested too deeply; a configuration is a few levels of "
                          "sections") from exc
    if doc is None:
        raise ConfigError(f"{source}: not a YAML mapping (empty); start from config/appliance.yaml "
                          "(every option with its default)")
    if not isinstance(doc, dict):
        kind = {list: "a list", str: "a single string", int: "a number", float: "a number",
                bool: "a boolean"}.get(type(doc), type(doc).__name__)
        raise ConfigError(f"{source}:1: not a YAML mapping ({kind}); the configuration is sections such as "
                          "'cameras:' and 'output:' (see config/appliance.yaml)")
    bad_keys = [k for k in doc if not isinstance(k, str)]
    if bad_keys:
        raise ConfigError(f"{source}:1: top-level key {bad_keys[0]!r} is not a name; sections are names such "
                          "as 'cameras' and 'output'")
    try:
        cfg = AppConfig.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, doc, root)) from exc
    if base_dir is not None:
        cfg = _resolve_paths(cfg, base_dir)
    if len(text) + sum(n for _, n in lifted.values()) > INLINE_MESH_NOTE_BYTES:
        for i, obj in enumerate(cfg.virtual_rig.scene):
            if obj.type == "mesh" and obj.path is None and len(obj.vertices_mm) > INLINE_MESH_NOTE_VERTICES:
                log.warning("%s: virtual_rig.scene.%d is an inline mesh of %d vertices and %d triangles; it is read "
                            "at every start and reload: put it in a PLY/OBJ/STL file and give its path "
                            "(virtual_rig.scene.%d.path)", source, i, len(obj.vertices_mm), len(obj.triangles), i)
    return cfg


def _lift_numeric_lists(text: str) -> tuple[str, dict[str, tuple[Any, int]]]:
    """Large flow lists of plain numbers (an inline mesh) parsed by the JSON decoder instead of YAML.

    libyaml still builds a Python node per scalar: an 8 MB inline mesh took ~30 s. A list is lifted only when it is
    the value of a key or a list item, longer than :data:`LIFT_MIN_CHARS`, holds nothing but digits, '.', '-',
    brackets, commas and white space, and parses as JSON: with no exponents, '+', '_' or leading zeros, YAML and JSON
    read such numbers alike (int or float). It is replaced by a placeholder and its newlines, so line numbers stay.
    Returns the new text and ``{placeholder: (value, length)}``.
    """
    lifted: dict[str, tuple[Any, int]] = {}
    if len(text) < LIFT_MIN_CHARS:
        return text, lifted
    parts, end = [], 0
    for m in _LIST_START.finditer(text):
        start = m.end() - 1
        if start < end:
            continue
        line_start = text.rfind("\n", 0, start) + 1
        if any(c in text[line_start:start] for c in "#'\""):
            continue  # in a comment or a quoted scalar
        try:
            value, stop = _JSON.raw_decode(text, start)
        except ValueError:
            continue
        after = _AFTER_LIST.match(text, stop)
        if stop - start < LIFT_MIN_CHARS or not isinstance(value, list) or after is None or \
                _NUMERIC_LIST.fullmatch(text, start, stop) is None:
            continue
        key = f"__scan3d_inline_list_{len(lifted)}__"
        if key in text:
            continue
        lifted[key] = (value, stop - start)
        parts += [text[end:start], key, "\n" * text.count("\n", start, stop)]
        end = stop
    if not lifted:
        return text, lifted
    parts.append(text[end:])
    return "".join(parts), lifted


def _put_back(doc: Any, lifted: dict[str, tuple[Any, int]], used: set[str]) -> Any:
    """``doc`` with each placeholder string of :func:`_lift_numeric_lists` replaced by its list."""
    if isinstance(doc, str) and doc in lifted:
        used.add(doc)
        return lifted[doc][0]
    if isinstance(doc, dict):
        return {k: _put_back(v, lifted, used) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_put_back(v, lifted, used) for v in doc]
    return doc


def _parse_fast(text: str) -> tuple[Any, yaml.Node | None, dict[str, tuple[Any, int]]]:
    """:func:`parse_yaml` with large numeric lists lifted out (:func:`_lift_numeric_lists`); should the lifted
    text not parse, or a placeholder land anywhere but as a whole value, the original text is parsed as it is
    (its result and its errors are the authority)."""
    short, lifted = _lift_numeric_lists(text)
    if lifted:
        try:
            doc, root = parse_yaml(short)
            used: set[str] = set()
            doc = _put_back(doc, lifted, used)
            if used == set(lifted):
                return doc, root, lifted
        except (yaml.YAMLError, RecursionError):
            pass
    doc, root = parse_yaml(text)
    return doc, root, {}


def _resolve_paths(cfg: AppConfig, base: Path) -> AppConfig:
    scene = []
    changed = False
    for obj in cfg.virtual_rig.scene:
        if obj.type == "mesh" and obj.path is not None and not obj.path.is_absolute():
            obj = obj.model_copy(update={"path": base / obj.path})
            changed = True
        scene.append(obj)
    if not changed:
        return cfg
    rig = cfg.virtual_rig.model_copy(update={"scene": tuple(scene)})
    return cfg.model_copy(update={"virtual_rig": rig})


def load_config(path: str | Path) -> AppConfig:
    """Read and validate a configuration file (see :func:`parse_config`)."""
    p = Path(path)
    data = read_bytes_file(p, what="configuration", error=ConfigError, limit_bytes=MAX_CONFIG_BYTES,
                           fix="check the path or pass --config FILE")
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise ConfigError(f"{p}: not a YAML mapping (binary data: UTF-16 text); save the file as UTF-8 text")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        kind = "binary data" if b"\x00" in data else "not UTF-8 text"
        raise ConfigError(f"{p}: not a YAML mapping ({kind}: byte 0x{data[exc.start]:02x} at offset {exc.start}); "
                          "save the file as UTF-8 text") from exc
    return parse_config(text, str(p), p.parent)


def _readable_file(path: Path) -> str:
    """'' when ``path`` is a regular file this process can read, else why not (a FIFO is not opened)."""
    if "\x00" in str(path):  # os.stat raises ValueError
        return "holds a NUL character"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "does not exist"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if stat.S_ISDIR(st.st_mode):
        return "is a folder, not a file"
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file (a FIFO, a device or a socket)"
    if not os.access(path, os.R_OK):
        return "cannot be read (permission denied)"
    return ""


MAX_SOCKET_PATH = 107
"""Longest unix socket path (bytes; sun_path holds 108 with the final NUL)."""


def folder_problem(folder: Path, writable: bool) -> str:
    """'' when ``folder`` is a folder (writable, if asked) or can be made; else why not.

    Parameters
    ----------
    folder : Path
        The folder.
    writable : bool
        Whether it (or the folder it would be made in) must be writable.

    Returns
    -------
    str
        Empty when all is well, else the reason (``"is a file, not a folder"``, ...).
    """
    text = str(folder)
    if "\x00" in text:
        return "holds a NUL character"
    target = Path(os.path.abspath(text))
    cur = target
    while True:
        try:
            st = os.stat(cur)
            break
        except (FileNotFoundError, NotADirectoryError):
            if cur == cur.parent:
                return "cannot be created (no existing folder above it)"
            cur = cur.parent
        except OSError as exc:
            return f"cannot be checked ({exc.strerror or exc})"
    if not stat.S_ISDIR(st.st_mode):
        return "is a file, not a folder" if cur == target else f"cannot be created: '{cur}' is a file, not a folder"
    if writable and not os.access(cur, os.W_OK | os.X_OK):
        return "is not writable" if cur == target else f"cannot be created: '{cur}' is not writable"
    return ""


def check_files(cfg: AppConfig, source: str = "<config>") -> list[str]:
    """What can be checked about a valid configuration without hardware: the files it names and its folders.

    Parameters
    ----------
    cfg : AppConfig
        A configuration that passed :func:`parse_config`.
    source : str
        The file name used in messages.

    Returns
    -------
    list of str
        One ``file: key = value: problem; fix`` line per problem (empty when all is well): the calibration file
        present and readable, every mesh of the virtual scene present, the state, spool and socket folders
        (or creatable, and writable), the share not a file, the control socket's path short enough for
        a unix socket, the spool folder neither the share nor inside it (nor the share inside the spool).
    """
    problems = []
    if cfg.calibration_file is not None:
        why = _readable_file(cfg.calibration_file)
        if why:
            problems.append(f"{source}: calibration_file = '{cfg.calibration_file}': {why}; run scan3d calibrate "
                            "or fix the path (relative paths are from the service's working folder)")
    for i, obj in enumerate(cfg.virtual_rig.scene):
        path = getattr(obj, "path", None)
        if obj.type == "mesh" and path is not None:
            why = _readable_file(path)
            if why:
                problems.append(f"{source}: virtual_rig.scene.{i}.path = '{path}': {why}; fix the path (relative "
                                "to the configuration file)")
    for key, folder, writable, fix in (
            ("service.state_directory", cfg.service.state_directory, True, "the service keeps its counters and "
             "calibration health there"),
            ("output.spool_directory", cfg.output.spool_directory, True, "scans wait there while the share is away"),
            ("output.directory", cfg.output.directory, False, "clouds are written there (a share that is away "
             "is spooled for, a file in its place is not)"),
            ("service.control_socket", cfg.service.control_socket.parent, True, "the control socket is made there")):
        why = folder_problem(folder, writable)
        if why:
            problems.append(f"{source}: {key} = '{folder}': {why}; {fix}")
    sock = os.fsencode(str(cfg.service.control_socket))
    with contextlib.suppress(OSError, ValueError):  # absent (made at start) or unreadable: said above
        if not stat.S_ISSOCK(os.lstat(cfg.service.control_socket).st_mode):  # scan3d run refuses to replace it
            problems.append(f"{source}: service.control_socket = '{cfg.service.control_socket}': a file that is not "
                            "a socket is there; remove it or choose another path")
    if len(sock) > MAX_SOCKET_PATH:
        problems.append(f"{source}: service.control_socket = '{cfg.service.control_socket}': {len(sock)} bytes is "
                        f"longer than a unix socket path may be ({MAX_SOCKET_PATH}); use a shorter path such as "
                        "/run/scan3d/control.sock")
    if any("\x00" in str(p) for p in (cfg.output.directory, cfg.output.spool_directory)):
        return problems
    share = Path(os.path.abspath(cfg.output.directory))
    spool = Path(os.path.abspath(cfg.output.spool_directory))
    if share == spool or share in spool.parents or spool in share.parents:
        relation = ("is the share" if share == spool else
                    "is inside the share" if share in spool.parents else "contains the share")
        problems.append(f"{source}: output.spool_directory = '{cfg.output.spool_directory}' {relation} "
                        f"(output.directory = '{cfg.output.directory}'); the spool must be a separate local "
                        "folder (e.g. /var/lib/scan3d/spool), or watchers see spooled scans and a share that is "
                        "away takes the spool with it")
    return problems


SERVICE_FOLDERS = (
    ("service.state_directory", "the service keeps its scan counter and calibration health there",
     "/var/lib/scan3d/state"),
    ("output.spool_directory", "scans wait there while the share is away", "/var/lib/scan3d/spool"),
)
"""The local folders ``scan3d run`` needs before it may say ready: key, what it is for, an example."""


def prepare_service_folders(cfg: AppConfig, source: str = "<config>") -> None:
    """Make the service's local folders (state, spool) and check they are writable, before it reports ready.

    Parameters
    ----------
    cfg : AppConfig
        The configuration the service runs.
    source : str
        The configuration file's name, for the message.

    Raises
    ------
    ConfigError
        One line naming the key, the folder, the rule (a writable folder, or one that can be made) and the
        fix, when a folder is a file, lies under a file, holds a NUL, cannot be made or is read-only.
    """
    for key, why_needed, example in SERVICE_FOLDERS:
        section, name = key.split(".")
        folder = Path(getattr(getattr(cfg, section), name))
        why = folder_problem(folder, writable=True)
        if not why:
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                why = f"cannot be created ({exc.strerror or exc})"
        if not why and not os.access(folder, os.W_OK | os.X_OK):
            why = "is not writable"
        if why:
            raise ConfigError(f"{source}: {key} = '{folder}': {why}; it must be a writable folder "
                              f"({why_needed}): make it one or point {key} at one (e.g. {example})")
