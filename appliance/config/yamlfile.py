"""Reading the appliance's YAML files safely: regular files only, a size limit, one parse, duplicate keys refused.

Configurations, manifests and calibrations are all read through :func:`read_text_file` (a FIFO, a device or a
folder is refused without being read, so nothing blocks; a file over the limit is refused before it is read)
and the YAML ones through :func:`parse_yaml` (libyaml when installed; the node tree and the document come from
one parse; a key given twice in one mapping is an error naming both lines instead of the last one winning).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from appliance.errors import ApplianceError

try:  # libyaml is ~10x faster than the pure-Python parser on large files (an inline mesh)
    from yaml import CSafeLoader as _BaseLoader
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    from yaml import SafeLoader as _BaseLoader  # type: ignore[assignment]

MB = 1024 * 1024


def _kind_of(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def read_bytes_file(path: str | os.PathLike[str], *, what: str, error: type[ApplianceError],
                    limit_bytes: int, fix: str = "check the path") -> bytes:
    """The bytes of a regular file of at most ``limit_bytes``, never blocking.

    Parameters
    ----------
    path : path-like
        The file.
    what : str
        What the file is, for messages (``"configuration"``, ``"manifest"``).
    error : type
        The :class:`ApplianceError` subclass raised.
    limit_bytes : int
        Largest accepted size (bytes).
    fix : str
        What to do when the file is missing or unreadable.

    Raises
    ------
    ApplianceError
        (``error``) One line: missing, unreadable, not a regular file (FIFO, device, folder), or too large.
    """
    p = Path(path)
    try:
        st = os.stat(p)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{p}: is {_kind_of(st.st_mode)}, not a regular file; a {what} must be a plain file")
        # O_NONBLOCK: should the path become a FIFO between stat and open, open does not wait for a writer
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc}); {fix}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{p}: is {_kind_of(st.st_mode)}, not a regular file; a {what} must be a plain file")
        if st.st_size > limit_bytes:
            raise error(f"{p}: {st.st_size / MB:.1f} MB is too large for a {what} (limit "
                        f"{limit_bytes / MB:.0f} MB); check that this is the right file")
        chunks = []
        total = 0
        while total <= limit_bytes:
            chunk = os.read(fd, min(MB, limit_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        if total > limit_bytes:
            raise error(f"{p}: grew beyond {limit_bytes / MB:.0f} MB while being read; a {what} must not be "
                        "written while it is read")
        return b"".join(chunks)
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc}); {fix}") from exc
    finally:
        os.close(fd)


def read_text_file(path: str | os.PathLike[str], *, what: str, error: type[ApplianceError],
                   limit_bytes: int, fix: str = "check the path") -> str:
    """The UTF-8 text of a regular file (see :func:`read_bytes_file`); binary and UTF-16 files are refused.

    Raises
    ------
    ApplianceError
        (``error``) As :func:`read_bytes_file`, or the content is not UTF-8 text (NUL bytes, a UTF-16 mark).
    """
    data = read_bytes_file(path, what=what, error=error, limit_bytes=limit_bytes, fix=fix)
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise error(f"{path}: not a YAML {what} (binary data: UTF-16 text); save the file as UTF-8 text")
    if b"\x00" in data:
        raise error(f"{path}: not a YAML {what} (binary data: a NUL byte at offset {data.index(0)}); "
                    "check that this is the right file")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a YAML {what} (not UTF-8 text: byte 0x{data[exc.start]:02x} at offset "
                    f"{exc.start}); save the file as UTF-8 text") from exc


class DuplicateKeyError(yaml.MarkedYAMLError):
    """A mapping states one key twice (both places are in the message)."""


def duplicate_key(node: yaml.MappingNode) -> tuple[yaml.ScalarNode, int] | None:
    """The first key of one mapping node that an earlier key of it already gave, and that earlier key's line
    (1-based); None when every key is given once (merge keys and non-scalar keys are not compared)."""
    seen: dict[str, int] = {}
    for key_node, _ in node.value:
        if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
            continue
        if key_node.value in seen:
            return key_node, seen[key_node.value]
        seen[key_node.value] = key_node.start_mark.line + 1
    return None


def duplicate_key_in(root: yaml.Node | None) -> tuple[str, int, int] | None:
    """The first key given twice in any mapping of a node tree (:func:`duplicate_key`): (key, first line, second
    line), for texts whose tags a safe loader does not construct (OpenCV's ``!!opencv-matrix``)."""
    todo = [root] if root is not None else []
    while todo:
        node = todo.pop()
        if isinstance(node, yaml.MappingNode):
            twice = duplicate_key(node)
            if twice is not None:
                return twice[0].value, twice[1], twice[0].start_mark.line + 1
            todo.extend(v for _, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            todo.extend(node.value)
    return None


class _Loader(_BaseLoader):
    """Safe YAML that refuses a key given twice in one mapping (YAML says keys are unique; PyYAML keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        twice = duplicate_key(node)
        if twice is not None:
            key_node, first = twice
            raise DuplicateKeyError(
                problem=f"key {key_node.value!r} is given twice (lines {first} and {key_node.start_mark.line + 1}); "
                "YAML would keep only the last, so remove one", problem_mark=key_node.start_mark)
        return super().construct_mapping(node, deep)


def parse_yaml(text: str) -> tuple[Any, yaml.Node | None]:
    """One parse of ``text``: the document and its node tree (for line numbers).

    Raises
    ------
    yaml.YAMLError
        Not valid YAML, or a duplicate key (:class:`DuplicateKeyError`, a ``MarkedYAMLError``).
    RecursionError
        Nested too deeply for the pure-Python parser (libyaml stops at 1000 levels with a YAMLError).
    """
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
        doc = loader.construct_document(root) if root is not None else None
    finally:
        loader.dispose()
    return doc, root


def yaml_problem(exc: yaml.YAMLError, source: str) -> tuple[str, str]:
    """``(where, problem)`` of a YAML error: ``file:line`` and the problem on one line."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = " ".join(str(exc.problem or exc).split())
        if "nesting depth" in problem:  # libyaml's limit
            problem = "nested too deeply (more than 1000 levels)"
        return where, problem
    return source, " ".join(str(exc).split())
