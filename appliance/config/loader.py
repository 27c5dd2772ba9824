"""Loading the YAML configuration with errors that name file, line, key path, value and rule."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from appliance.config.schema import AppConfig
from appliance.errors import ConfigError


def _node_at(root: yaml.Node | None, loc: tuple[int | str, ...]) -> yaml.Node | None:
    """The deepest YAML node along ``loc`` (pydantic's error location)."""
    node = root
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            nxt = None
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    nxt = v if not _is_last(loc, key) else k
                    break
            if nxt is None:
                return node
            node = nxt
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
    """One line per problem: ``file:line: key.path = value: rule``."""
    lines = []
    for err in exc.errors():
        loc = _clean_loc(tuple(err["loc"]), doc)
        path = ".".join(str(p) for p in loc) or "(top level)"
        node = _node_at(root, loc)
        line = f"{node.start_mark.line + 1}" if node is not None else "?"
        found, value = _lookup(doc, loc)
        rule = err["msg"]
        if err["type"] == "extra_forbidden":
            rule = "unknown key (check its spelling against config/appliance.yaml)"
        elif err["type"] == "missing":
            rule = "required key is missing"
        shown = f" = {value!r}" if found and not isinstance(value, dict | list) else ""
        lines.append(f"{source}:{line}: {path}{shown}: {rule}")
    return "\n".join(lines)


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
    try:
        root = yaml.compose(text)
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{where}: not valid YAML: {problem}; check indentation and quoting") from exc
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{source}:1: the configuration must be a YAML mapping of sections")
    try:
        cfg = AppConfig.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, doc, root)) from exc
    if base_dir is not None:
        cfg = _resolve_paths(cfg, base_dir)
    return cfg


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
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot be read ({exc.strerror}); check the path or pass --config FILE") from exc
    return parse_config(text, str(p), p.parent)
