"""Safe YAML loading that remembers where every value came from.

Mappings load as :class:`YMap` and sequences as :class:`YList`; both know the line of
the node and of each key or item, and the file that wrote each key or item, so that
validation errors can name ``file:line`` and the key path, also after a document was
merged with the file it ``extends`` (:mod:`symcal.language.overlay`).  Only
:class:`yaml.SafeLoader` constructors are used: no Python objects can be built from a
file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from symcal.errors import SpecError, Where


class YMap(dict):
    """A dict loaded from YAML, with ``line`` and per-key ``key_lines`` (1-based).

    ``key_files`` names, per key, the file that wrote it (as shown in messages); a key
    missing from it belongs to the file of the mapping's provenance.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.line: int | None = None
        self.key_lines: dict[Any, int] = {}
        self.key_files: dict[Any, str] = {}


class YList(list):
    """A list loaded from YAML, with ``line`` and per-item ``item_lines`` (1-based).

    ``item_files`` names, per item, the file that wrote it, like :attr:`YMap.key_files`.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.line: int | None = None
        self.item_lines: list[int] = []
        self.item_files: list[str] = []


class _Loader(yaml.SafeLoader):
    """SafeLoader that keeps line numbers and files and rejects duplicate keys."""

    source: str = ""


def _construct_map(loader: _Loader, node: yaml.MappingNode) -> YMap:
    loader.flatten_mapping(node)
    out = YMap()
    out.line = node.start_mark.line + 1
    out.key_lines = {}
    out.key_files = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        if not isinstance(key, (str, int, float, bool)) or key is None:
            raise yaml.constructor.ConstructorError(
                None, None, f"keys must be plain names, found {key!r}", key_node.start_mark
            )
        if key in out:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{key}' (first at line {out.key_lines[key]})",
                key_node.start_mark,
            )
        out[key] = loader.construct_object(value_node, deep=True)
        out.key_lines[key] = line
        out.key_files[key] = loader.source
    return out


def _construct_seq(loader: _Loader, node: yaml.SequenceNode) -> YList:
    out = YList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.item_lines = [child.start_mark.line + 1 for child in node.value]
    out.item_files = [loader.source] * len(node.value)
    return out


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_seq)


def _parse(text: str, source: str) -> Any:
    """One YAML document, its keys and items marked as written by ``source``."""
    loader = _Loader(text)
    loader.source = source
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def display_path(path: Path) -> str:
    """Path as shown in messages: relative to the working directory when below it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def load_yaml(path: str | Path, what: str = "file") -> tuple[YMap, Where]:
    """Load one YAML document whose top level must be a mapping.

    Parameters
    ----------
    path
        The file to read.
    what
        What the file is (``"model"``, ``"problem"``, ...), used in messages.

    Returns
    -------
    (YMap, Where)
        The document and the provenance of its top level.

    Raises
    ------
    SpecError
        If the file is missing, is not valid YAML, or its top level is not a mapping.
    """
    path = Path(path)
    shown = display_path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError(Where(shown), f"{what} file not found") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        reason = exc.__class__.__name__
        raise SpecError(Where(shown), f"cannot read {what} file ({reason})") from None
    try:
        doc = _parse(text, shown)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = exc.problem or str(exc)
        raise SpecError(Where(shown, line), f"invalid YAML: {problem}") from None
    except yaml.YAMLError as exc:
        raise SpecError(Where(shown), f"invalid YAML: {exc}") from None
    if not isinstance(doc, YMap):
        kind = "empty" if doc is None else f"a {type(doc).__name__}"
        raise SpecError(Where(shown, 1), f"a {what} file must be a mapping of keys, found {kind}")
    return doc, Where(shown, doc.line)
