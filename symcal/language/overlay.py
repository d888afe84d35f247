"""``extends:`` for problem and scenario files: a file as an overlay of another.

A file with a top-level ``extends: OTHER.yaml`` (relative to the file) is merged onto the
document of that file, which may extend another in turn; the merged document is then
validated as if it had been written in one file.  The merge works on loaded YAML (YMap,
YList) and keeps, per key, the file and line that wrote it, so that an error about a key
inherited from a base names the base's ``file:line`` and the file that was loaded.

How keys merge is the caller's *merge rule*: :func:`merge_problem` for problems and
:func:`merge_scenario` for scenarios.  In both, ``null`` removes what the base declares.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.base.files import LINK_LOOP, input_refusal, resolve
from symcal.language.courier import PRESETS
from symcal.language.fields import child_where, expect_str
from symcal.language.yamlio import MAX_BYTES, YList, YMap, display_path, load_yaml

#: How many files deep ``extends`` may go (a file and at most this many bases).
MAX_DEPTH = 32

#: ``merge_rule(base, overlay, base_path)`` returns the merged document.
MergeRule = Callable[[YMap, YMap, Path], YMap]
#: ``merge_entry(key, base_value, overlay_value)`` merges a key both files declare.
EntryRule = Callable[[Any, Any, Any], Any]

#: Problem sections merged entry by entry (``instances`` one level deeper).
KEYED_SECTIONS = ("constants", "parameters", "columns", "instances", "expressions",
                  "constraints", "comparisons", "datasets", "implicit", "noise")
#: Keys of an instance merged entry by entry.
INSTANCE_SECTIONS = ("inputs", "parameters", "noise", "constants")
#: Problem keys holding paths relative to the file, per keyed section.
PATH_KEYS = {"instances": ("model",), "datasets": ("path", "simulate")}


# --------------------------------------------------------------------------- loading


def load_with_extends(path: str | Path, what: str, merge_rule: MergeRule) -> tuple[YMap, Where]:
    """Load a YAML document and, if it ``extends`` another file, merge it onto that file.

    Parameters
    ----------
    path
        The file to read.
    what
        The kind of file (``"problem"``, ``"scenario"``); a base must be of the same
        kind, i.e. have this top-level key, which is not inherited: the file loaded must
        declare its own.
    merge_rule
        ``merge_rule(base, overlay, base_path)``: the overlay (without ``extends``)
        merged onto the base (without its ``what`` key).

    Returns
    -------
    (YMap, Where)
        The merged document, without ``extends``, and the provenance of the file's top
        level.  Each key knows the file and line that wrote it.

    Raises
    ------
    SpecError
        For a file that cannot be loaded, a base that is missing or of another kind, a
        cycle of files, or more than :data:`MAX_DEPTH` levels; an error in a base names
        the base's ``file:line`` and the file that was loaded.
    """
    path = Path(path)
    doc, where = load_yaml(path, what)
    if "extends" not in doc:
        return doc, where
    try:
        return _merged(doc, where, path, what, merge_rule, ()), where
    except SpecError as exc:
        raise _reached_through(exc, where.file) from None


def extends_chain(path: str | Path, what: str) -> tuple[Path, ...]:
    """The file and every file it extends, directly or not, in order (resolved paths).

    What a merged document depends on, e.g. to hash the sources of a result.

    Parameters
    ----------
    path
        The file.
    what
        The kind of file (``"problem"``, ``"scenario"``).

    Returns
    -------
    tuple of Path
        ``path`` first, then its base, the base's base, and so on.

    Raises
    ------
    SpecError
        As :func:`load_with_extends` for a missing base, a cycle or too many levels.
    """
    chain = [Path(path).resolve()]
    while True:
        doc, where = load_yaml(chain[-1], what)
        if "extends" not in doc:
            return tuple(chain)
        at = child_where(doc, where, "extends")
        chain.append(resolve_base(doc["extends"], at, chain[-1], what, tuple(chain)))


def _reached_through(exc: SpecError, top: str) -> SpecError:
    """``exc`` marked as reached through ``top`` when it is about another file."""
    if exc.where.file == top or exc.where.via is not None:
        return exc
    return SpecError(replace(exc.where, via=top), exc.detail)


def _merged(
    doc: YMap, where: Where, path: Path, what: str, rule: MergeRule, chain: tuple[Path, ...]
) -> YMap:
    """``doc`` (which has ``extends``) merged onto its bases, recursively."""
    at = child_where(doc, where, "extends")
    chain = (*chain, path.resolve())
    base_path = resolve_base(doc["extends"], at, path, what, chain)
    base, base_where = load_yaml(base_path, what)
    if what not in base:
        raise SpecError(at, f"{display_path(base_path)} is not a {what} file (it has no "
                            f"'{what}' key); a {what} can only extend a {what}")
    if "extends" in base:
        base = _merged(base, base_where, base_path, what, rule, chain)
    return rule(without(base, [what]), without(doc, ["extends"]), base_path)


def resolve_base(value: Any, at: Where, path: Path, what: str, chain: tuple[Path, ...]) -> Path:
    """The file ``extends: value`` names, checked against cycles, depth and absence."""
    if isinstance(value, str) and not value.strip():
        raise SpecError(at, f"an empty file name; name the {what} file this one extends, or "
                            "remove 'extends'")
    named = path.parent / expect_str(value, at)
    try:
        target = resolve(named)
    except OSError:
        raise SpecError(at, f"{display_path(named)} is {LINK_LOOP}") from None
    if target in chain:
        names = " -> ".join(display_path(p) for p in (*chain, target))
        raise SpecError(at, f"{what}s extend each other in a cycle: {names}")
    if len(chain) > MAX_DEPTH:
        raise SpecError(at, f"more than {MAX_DEPTH} levels of 'extends' below "
                            f"{display_path(chain[0])}")
    if not target.exists():
        raise SpecError(at, f"{what} file not found: {display_path(target)}")
    reason = input_refusal(target, MAX_BYTES)
    if reason is not None:
        raise SpecError(at, f"cannot read {what} file {display_path(target)}: it {reason}")
    return target


# --------------------------------------------------------------------------- building blocks


def new_map(line: int | None) -> YMap:
    """An empty :class:`YMap` at ``line`` with per-key provenance."""
    out = YMap()
    out.line = line
    out.key_lines = {}
    out.key_files = {}
    return out


def new_list(line: int | None) -> YList:
    """An empty :class:`YList` at ``line`` with per-item provenance."""
    out = YList()
    out.line = line
    out.item_lines = []
    out.item_files = []
    return out


def put(out: YMap, src: YMap, key: Any, value: Any = None, *, same: bool = True) -> None:
    """Set ``out[key]`` with the provenance ``key`` has in ``src`` (value: ``src[key]``)."""
    out[key] = src[key] if same else value
    if key in src.key_lines:
        out.key_lines[key] = src.key_lines[key]
    if key in src.key_files:
        out.key_files[key] = src.key_files[key]


def append(out: YList, src: YList, index: int) -> None:
    """Append ``src[index]`` to ``out`` with its provenance."""
    out.append(src[index])
    out.item_lines.append(_at(src.item_lines, index, src.line))
    out.item_files.append(_at(src.item_files, index, ""))


def _at(items: Any, index: int, default: Any) -> Any:
    return items[index] if index < len(items) else default


def without(doc: YMap, keys: Iterable[Any]) -> YMap:
    """A copy of ``doc`` without ``keys``, provenance kept."""
    skip = set(keys)
    out = new_map(doc.line)
    for key in doc:
        if key not in skip:
            put(out, doc, key)
    return out


def merge_keyed(base: Any, overlay: Any, merge_entry: EntryRule | None = None) -> Any:
    """Merge two mappings key by key: replace, add, and remove on ``null``.

    Parameters
    ----------
    base, overlay
        The two values; unless both are mappings the overlay's replaces the base's.
    merge_entry
        ``merge_entry(key, base_value, overlay_value)`` for a key both declare (default:
        the overlay's value replaces the base's).

    Returns
    -------
    Any
        The merged mapping: the base's keys in their order (an overlay's ``KEY: null``
        removes the key), then the overlay's new keys (a new ``null`` stays, to mean what
        it means in a file of its own).
    """
    if not (isinstance(base, YMap) and isinstance(overlay, YMap)):
        return overlay
    out = new_map(overlay.line)
    for key, value in base.items():
        if key not in overlay:
            put(out, base, key)
        elif overlay[key] is not None:
            entry = overlay[key] if merge_entry is None else merge_entry(key, value, overlay[key])
            put(out, overlay, key, entry, same=False)
    for key in overlay:
        if key not in base:
            put(out, overlay, key)
    return out


# --------------------------------------------------------------------------- problems


def merge_problem(base: YMap, overlay: YMap, base_path: Path) -> YMap:
    """Merge a problem file onto the problem it extends.

    Top-level values replace the base's; the sections of :data:`KEYED_SECTIONS` merge
    entry by entry (an entry replaces the base's entry of the same name, a new one is
    added, ``NAME: null`` removes the base's); an instance merges one level deeper (its
    ``inputs`` and ``parameters`` by key); ``stages`` merge by ``name`` (same name
    replaces in place, a new one is appended, ``{name: X, remove: true}`` removes X).
    Paths the base writes (instances' ``model``, datasets' ``path`` and ``simulate``)
    stay relative to the base file: they are made absolute.

    Parameters
    ----------
    base
        The base document, without its ``problem`` key.
    overlay
        The extending document, without ``extends``.
    base_path
        The base's file.

    Returns
    -------
    YMap
        The merged document.
    """
    return _redeclared(merge_keyed(_rebase_paths(base, base_path), overlay, _merge_section),
                       overlay)


def _redeclared(merged: YMap, overlay: YMap) -> YMap:
    """A name the overlay declares as a parameter that the base declares as a constant
    (or the other way round) leaves the base's section: an overlay may make a constant a
    parameter (``parameters: {l_s: {value: 9.7, unit: mm}}``), or fix one as a constant."""
    for new, old in (("parameters", "constants"), ("constants", "parameters")):
        added, section = overlay.get(new), merged.get(old)
        if not (isinstance(added, YMap) and isinstance(section, YMap)):
            continue
        mine = overlay.get(old)
        moved = [k for k, v in added.items() if v is not None and k in section
                 and not (isinstance(mine, YMap) and k in mine)]
        if moved:
            put(merged, merged, old, without(section, moved), same=False)
    return merged


def _merge_section(key: Any, base: Any, overlay: Any) -> Any:
    """One top-level key of a problem that both files declare."""
    if key == "columns" and isinstance(base, str) and base in PRESETS \
            and isinstance(overlay, YMap):   # columns added to a preset's
        return merge_keyed(_preset(base, overlay.line), overlay)
    if key == "instances":
        return merge_keyed(base, overlay, lambda _, b, o: merge_keyed(b, o, _merge_instance))
    if key in KEYED_SECTIONS:
        return merge_keyed(base, overlay)
    if key == "stages":
        return _merge_stages(base, overlay)
    return overlay


def _preset(name: str, line: int | None) -> YMap:
    """The columns of preset ``name`` as the mapping a file would write."""
    out = new_map(line)
    for column, (unit, role, doc, noise) in PRESETS[name].items():
        entry = new_map(line)
        for k, v in (("unit", unit), ("role", role), ("doc", doc), ("noise", noise)):
            if v:
                entry[k] = v
        out[column] = entry
    return out


def _merge_instance(key: Any, base: Any, overlay: Any) -> Any:
    """One key of an instance: ``inputs`` and ``parameters`` merge by key, others replace."""
    return merge_keyed(base, overlay) if key in INSTANCE_SECTIONS else overlay


def _rebase_paths(base: YMap, base_path: Path) -> YMap:
    """``base`` with the relative paths it writes made absolute (relative to its file)."""
    out = without(base, [])
    for section, keys in PATH_KEYS.items():
        entries = base.get(section)
        if isinstance(entries, YMap):
            rebased = new_map(entries.line)
            for name, entry in entries.items():
                put(rebased, entries, name, _rebase_entry(entry, keys, base_path), same=False)
            put(out, base, section, rebased, same=False)
    return out


def _rebase_entry(entry: Any, keys: tuple[str, ...], base_path: Path) -> Any:
    """An instance or dataset with its path values made absolute."""
    if not isinstance(entry, YMap):
        return entry
    out = without(entry, [])
    for key in keys:
        value = entry.get(key)
        if isinstance(value, str) and value.strip():
            put(out, entry, key, str((base_path.parent / value).resolve()), same=False)
    return out


def _merge_stages(base: Any, overlay: Any) -> Any:
    """Stages by ``name``: replace in place, append, or ``{name: X, remove: true}``."""
    if not (isinstance(base, YList) and isinstance(overlay, YList)):
        return overlay
    out = new_list(overlay.line)
    for index in range(len(base)):
        append(out, base, index)
    seen: set[Any] = set()
    for index, item in enumerate(overlay):
        name = item.get("name") if isinstance(item, YMap) else None
        if isinstance(name, str) and "remove" in item:
            _remove_stage(out, item, name, _item_where(overlay, index))
        elif isinstance(name, str) and name not in seen and name in _names(out):
            _replace_stage(out, overlay, index, _names(out).index(name))
        else:
            append(out, overlay, index)
        seen.add(name)
    return out


def _item_where(items: YList, index: int) -> Where:
    """Provenance of ``stages[index]`` in the file that wrote it."""
    return Where(_at(items.item_files, index, ""), _at(items.item_lines, index, items.line),
                 f"stages.{index}")


def _names(stages: YList) -> list[Any]:
    return [item.get("name") if isinstance(item, YMap) else None for item in stages]


def _replace_stage(out: YList, overlay: YList, index: int, position: int) -> None:
    out[position] = overlay[index]
    out.item_lines[position] = _at(overlay.item_lines, index, overlay.line)
    out.item_files[position] = _at(overlay.item_files, index, "")


def _remove_stage(out: YList, item: YMap, name: str, at: Where) -> None:
    """Remove stage ``name`` as ``{name: X, remove: true}`` asks."""
    if item["remove"] is not True:
        raise SpecError(child_where(item, at, "remove"),
                        f"expected true (to remove stage '{name}'), found {item['remove']!r}")
    extra = [key for key in item if key not in ("name", "remove")]
    if extra:
        raise SpecError(child_where(item, at, extra[0]), f"a stage to remove takes only "
                                                         f"'name' and 'remove', found '{extra[0]}'")
    names = _names(out)
    if name not in names:
        known = [str(n) for n in names if n is not None]
        raise SpecError(child_where(item, at, "name"),
                        f"no stage '{name}' to remove{did_you_mean(name, known)}; "
                        f"stages: {', '.join(known) or 'none'}")
    position = names.index(name)
    del out[position], out.item_lines[position], out.item_files[position]


# --------------------------------------------------------------------------- scenarios


def merge_scenario(base: YMap, overlay: YMap, base_path: Path) -> YMap:
    """Merge a scenario file onto the scenario it extends.

    Mappings merge recursively at every level; lists and other values replace the
    base's; ``null`` removes the key (``platen: {effects: null}`` drops every effect).

    Parameters
    ----------
    base
        The base document, without its ``scenario`` key.
    overlay
        The extending document, without ``extends``.
    base_path
        The base's file (unused: scenarios hold no paths).

    Returns
    -------
    YMap
        The merged document.
    """
    del base_path
    return merge_keyed(base, overlay, _merge_deep)


def _merge_deep(key: Any, base: Any, overlay: Any) -> Any:
    """Mappings merge recursively; anything else replaces."""
    return merge_keyed(base, overlay, _merge_deep)
