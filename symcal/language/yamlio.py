"""Safe YAML loading that remembers where every value came from.

Mappings load as :class:`YMap` and sequences as :class:`YList`; both know the line of
the node and of each key or item, and the file that wrote each key or item, so that
validation errors can name ``file:line`` and the key path, also after a document was
merged with the file it ``extends`` (:mod:`symcal.language.overlay`).  Only
:class:`yaml.SafeLoader` constructors are used: no Python objects can be built from a
file.

Files symcal writes for itself or a person to read again (revisions, overlays, designed
scenarios) are written by :func:`dump_yaml` and :func:`yaml_scalar`, the emitter with the
same core schema: any text (a path with ``#``, ``: ``, quotes, brackets, a leading
digit or unicode) is quoted exactly when the loader would otherwise read it as something
else, never by string formatting.

Scalars resolve by the YAML 1.2 core schema, not PyYAML's YAML 1.1 rules: ``010`` is 10,
``1:30`` and ``yes`` are text, ``1e-3`` and ``-.5`` are numbers, ``0x1F`` and ``0o17`` are
integers.  Files are bounded before they are trusted: at most :data:`MAX_BYTES` bytes of
UTF-8 in a regular file, nested at most :data:`MAX_NESTING` levels, and at most
:data:`MAX_NODES` nodes once every alias is expanded (an alias counts as what it repeats).
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import yaml

from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.files import display_path, read_input_bytes
from symcal.base.forks import ForkLock

#: Largest YAML file accepted, in bytes.
MAX_BYTES = 1 << 20
#: Deepest nesting of mappings and lists accepted.
MAX_NESTING = 64
#: Most nodes a document may hold with every alias expanded.
MAX_NODES = 200_000
#: Most digits of an integer (a double holds at most 309 before the point).
MAX_DIGITS = 1000

__all__ = ["MAX_BYTES", "MAX_NESTING", "MAX_NODES", "YList", "YMap", "display_path",
           "dump_yaml", "load_yaml", "parse_yaml", "yaml_scalar"]


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
    """SafeLoader that keeps line numbers and files and rejects duplicate keys.

    It resolves scalars by the YAML 1.2 core schema and bounds nesting and the expanded
    size of the document while composing it.
    """

    source: str = ""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.depth = 0
        self.sizes: dict[int, int] = {}

    def compose_node(self, parent: Any, index: Any) -> Any:
        """Compose one node, refusing deep nesting and documents that expand too far."""
        self.depth += 1
        if self.depth > MAX_NESTING:
            raise yaml.composer.ComposerError(
                None, None, f"nested more than {MAX_NESTING} levels deep",
                self.peek_event().start_mark)
        try:
            node = super().compose_node(parent, index)
        finally:
            self.depth -= 1
        size = self.sizes.get(id(node))
        if size is None:
            size = 1
            if isinstance(node, yaml.SequenceNode):
                size += sum(self.sizes.get(id(child), 1) for child in node.value)
            elif isinstance(node, yaml.MappingNode):
                size += sum(self.sizes.get(id(k), 1) + self.sizes.get(id(v), 1)
                            for k, v in node.value)
            self.sizes[id(node)] = size
        if size > MAX_NODES:
            raise yaml.composer.ComposerError(
                None, None, f"the document expands to more than {MAX_NODES} nodes (an alias "
                            "counts as what it repeats)", node.start_mark)
        return node


def _core_schema() -> None:
    """Resolve plain scalars by the YAML 1.2 core schema (and keep ``<<`` merge keys)."""
    _Loader.yaml_implicit_resolvers = {}
    rules = [
        ("tag:yaml.org,2002:null", r"~|null|Null|NULL|", "~nN"),
        ("tag:yaml.org,2002:bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
        ("tag:yaml.org,2002:int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
        ("tag:yaml.org,2002:float",
         r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
         r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)", "-+.0123456789"),
        ("tag:yaml.org,2002:merge", r"<<", "<"),
    ]
    for tag, pattern, first in rules:
        _Loader.add_implicit_resolver(tag, re.compile(f"^(?:{pattern})$"), list(first))
    _Loader.add_implicit_resolver("tag:yaml.org,2002:null", re.compile("^$"), [""])


def _construct_int(loader: _Loader, node: yaml.ScalarNode) -> int:
    text = str(loader.construct_scalar(node))
    try:
        if text[:2] in ("0o", "0x"):
            return int(text[2:], 8 if text[1] == "o" else 16)
        if len(text) > MAX_DIGITS:
            raise ValueError(f"more than {MAX_DIGITS} digits")
        return int(text, 10)
    except ValueError:
        what = (f"has more than {MAX_DIGITS} digits" if len(text) > MAX_DIGITS
                else "is not an integer")
        raise yaml.constructor.ConstructorError(
            None, None, f"'{excerpt(text)}' {what}", node.start_mark) from None


def _construct_float(loader: _Loader, node: yaml.ScalarNode) -> float:
    text = str(loader.construct_scalar(node))
    special = {".inf": "inf", "+.inf": "inf", "-.inf": "-inf", ".nan": "nan"}
    try:
        return float(special.get(text.lower(), text))
    except ValueError:
        raise yaml.constructor.ConstructorError(
            None, None, f"'{excerpt(text)}' is not a number", node.start_mark) from None


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
                None, None, f"keys must be plain names, found {excerpt(repr(key))}",
                key_node.start_mark
            )
        if key in out:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{excerpt(key)}' (first at line "
                            f"{out.key_lines[key]})",
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
_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _construct_float)
_core_schema()


#: Documents parsed in this process, by (source, text): a loop that loads revisions of one
#: problem (``improve``: each revision extends the last and shares its model files) parses
#: each file once.  A copy is handed out, so no caller sees another's changes.
_PARSED: dict[tuple[str, str], Any] = {}
_PARSED_LOCK = ForkLock()
#: At most this many documents are kept (the oldest go first).
PARSED_KEPT = 256


def _parse(text: str, source: str) -> Any:
    """One YAML document, its keys and items marked as written by ``source``."""
    key = (source, text)
    with _PARSED_LOCK:
        doc = _PARSED.get(key)
    if doc is None:
        doc = _parse_now(text, source)     # a failure raises: nothing is kept
        with _PARSED_LOCK:
            _PARSED[key] = doc
            while len(_PARSED) > PARSED_KEPT:
                del _PARSED[next(iter(_PARSED))]
    return copy.deepcopy(doc)


def _parse_now(text: str, source: str) -> Any:
    loader = _Loader(text)
    loader.source = source
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


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
    text = _read_text(path, shown, what)
    try:
        doc = _parse(text, shown)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = excerpt(exc.problem or str(exc), 160)
        raise SpecError(Where(shown, line), f"invalid YAML: {problem}") from None
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        raise SpecError(Where(shown, line), f"invalid YAML: unacceptable character "
                                            f"#x{exc.character:04x}: {exc.reason}") from None
    except yaml.YAMLError as exc:
        raise SpecError(Where(shown), f"invalid YAML: {excerpt(exc, 200)}") from None
    except RecursionError:
        raise SpecError(Where(shown), "invalid YAML: nested too deeply") from None
    if not isinstance(doc, YMap):
        kind = "empty" if doc is None else f"a {type(doc).__name__}"
        raise SpecError(Where(shown, 1), f"a {what} file must be a mapping of keys, found {kind}")
    return doc, Where(shown, doc.line)


def _read_text(path: Path, shown: str, what: str) -> str:
    """The UTF-8 text of a YAML file, refusing what is not a bounded regular file."""
    label = what if what == "file" else f"{what} file"
    try:
        data = read_input_bytes(path, MAX_BYTES)
    except FileNotFoundError:
        raise SpecError(Where(shown), f"{label} not found") from None
    except OSError as exc:
        raise SpecError(Where(shown), f"cannot read {label}: "
                                      f"{exc.strerror or exc.__class__.__name__}") from None
    except ValueError as exc:
        raise SpecError(Where(shown), f"cannot read {label}: it {exc}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise SpecError(Where(shown, line), f"cannot read {label}: not UTF-8 text (byte "
                                            f"0x{data[exc.start]:02x} at offset {exc.start})"
                        ) from None


# --------------------------------------------------------------------------- writing

class _Dumper(yaml.SafeDumper):
    """SafeDumper that quotes text by the loader's rules (the YAML 1.2 core schema)."""


_Dumper.yaml_implicit_resolvers = {k: list(v) for k, v in _Loader.yaml_implicit_resolvers.items()}


def _represent_float(dumper: yaml.SafeDumper, value: float) -> yaml.ScalarNode:
    """Floats as the shortest text that reads back the same (``0.001``, ``1e-05``)."""
    if value != value:
        text = ".nan"
    elif value in (float("inf"), float("-inf")):
        text = ".inf" if value > 0 else "-.inf"
    else:
        text = repr(value)
    return dumper.represent_scalar("tag:yaml.org,2002:float", text)


def _represent_str(dumper: yaml.SafeDumper, value: str) -> yaml.ScalarNode:
    """Text with a line break or another character that is not printable (NEL, ESC) in
    double quotes, where it is escaped; other text as the emitter sees fit."""
    printable = all(ch.isprintable() or ch == " " for ch in value)
    return dumper.represent_scalar("tag:yaml.org,2002:str", value,
                                   style=None if printable else '"')


def _represent_map(dumper: yaml.SafeDumper, value: dict) -> yaml.MappingNode:
    return dumper.represent_dict(dict(value))


def _represent_list(dumper: yaml.SafeDumper, value: list) -> yaml.SequenceNode:
    return dumper.represent_list(list(value))


class _Block(dict):
    """A mapping always written as a block (a top-level section)."""


def _represent_block(dumper: yaml.SafeDumper, value: _Block) -> yaml.MappingNode:
    node = dumper.represent_dict(dict(value))
    node.flow_style = False
    return node


_Dumper.add_representer(_Block, _represent_block)
_Dumper.add_representer(float, _represent_float)
_Dumper.add_representer(str, _represent_str)
_Dumper.add_representer(YMap, _represent_map)
_Dumper.add_representer(YList, _represent_list)
_Dumper.add_representer(tuple, _represent_list)


def dump_yaml(doc: Any) -> str:
    """YAML text of plain data that :func:`load_yaml` reads back equal.

    Keys keep their order; the top level's sections are blocks, and below them a mapping
    or list of scalars is written on one line (``{value: 0, unit: mm}``); text is quoted
    only where it must be.
    """
    if isinstance(doc, dict):
        doc = _Block({k: _Block(v) if isinstance(v, dict) else v for k, v in doc.items()})
    return yaml.dump(doc, Dumper=_Dumper, sort_keys=False, default_flow_style=None,
                     allow_unicode=True, width=1 << 16)


def yaml_scalar(value: Any) -> str:
    """One scalar as YAML text that reads back equal in a block or a flow collection
    (``prob.yaml``, ``'runs #2/prob.yaml'``, ``"a\\nb"``)."""
    text = yaml.dump([value], Dumper=_Dumper, default_flow_style=True, allow_unicode=True,
                     width=1 << 16).strip()
    return text[1:-1].strip()


def parse_yaml(text: str, source: str = "<text>") -> Any:
    """The document of YAML ``text`` by the loader's rules (no size or file checks: for
    text symcal wrote itself)."""
    return _parse(text, source)
