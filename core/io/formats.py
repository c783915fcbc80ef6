"""The format table: which reader or writer handles which extension and kind.

Records go in (the :class:`~faceretarget.hookspecs.Reader` and ``Writer`` records the
plugin hooks returned, each with where it came from); lookups come out:

- :meth:`FormatTable.candidates`: the records for an extension (``"/"`` for a folder),
  optionally of one kind, in precedence order (highest ``priority`` first; on a tie
  built-ins first, then plugins in load order);
- :meth:`FormatTable.sniff_kind`: what an ambiguous file holds, asked of the sniffers the
  readers declare (``Reader.sniff``), each called once;
- :meth:`FormatTable.identify`: the registered formats whose magic bytes
  (``Reader.magic``) a file starts with ("this file is actually a PLY file");
- :meth:`FormatTable.rows`: every record with its precedence (which it shadows, which
  shadow it), for ``faceretarget formats``.

This module knows no plugin, no format and no registry: :mod:`faceretarget.io.builtin`
declares the built-in records, the registry collects every plugin's, and the dispatcher
(:mod:`faceretarget.io.dispatch`) builds a table from them when it needs one.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["Entry", "FormatTable", "MAGIC_BYTES", "ranked", "shadow_note"]

#: how many leading bytes :meth:`FormatTable.identify` reads (a longer magic never matches)
MAGIC_BYTES = 64


@dataclass(frozen=True)
class Entry:
    """One registered record (a Reader or a Writer) and where it came from."""

    record: Any
    origin: str  # "faceretarget 0.1.0", "someplugin 1.2", "local -"
    builtin: bool
    order: int  # position in load order

    @property
    def name(self) -> str:
        return self.record.name

    @property
    def kind(self) -> str:
        return self.record.kind

    @property
    def extensions(self) -> tuple[str, ...]:
        return tuple(self.record.extensions)

    @property
    def priority(self) -> float:
        return getattr(self.record, "priority", 0)

    def precedence(self) -> tuple:
        """Sort key: highest priority first; on a tie built-ins first, then load order."""
        return (-self.priority, not self.builtin, self.order)


def _entries(pairs: Iterable[tuple[Any, Any]]) -> list[Entry]:
    """``(record, info)`` pairs (``info`` has ``origin`` and ``builtin``, like the
    registry's ``PluginInfo``) as entries in load order."""
    return [
        Entry(rec, str(info.origin), bool(info.builtin), i) for i, (rec, info) in enumerate(pairs)
    ]


class FormatTable:
    """The readers and writers of one registry, looked up by name, extension and kind."""

    def __init__(
        self, readers: Iterable[tuple[Any, Any]] = (), writers: Iterable[tuple[Any, Any]] = ()
    ) -> None:
        self._entries = {"read": _entries(readers), "write": _entries(writers)}

    # -- lookups -------------------------------------------------------------------------
    def entries(self, direction: str) -> list[Entry]:
        """Every reader (``"read"``) or writer (``"write"``) in load order."""
        return list(self._entries[direction])

    def entry_of(self, direction: str, record: Any) -> Entry:
        """The entry holding ``record`` (the very object)."""
        return next(e for e in self._entries[direction] if e.record is record)

    def named(self, direction: str, name: str) -> list[Entry]:
        """The records called ``name``, in precedence order (normally one)."""
        return ranked(e for e in self._entries[direction] if e.name == name)

    def names(self, direction: str) -> list[str]:
        return sorted({e.name for e in self._entries[direction]})

    def extensions(self, direction: str, kind: str | None = None) -> list[str]:
        """Every extension read/written (of ``kind`` when given), sorted."""
        return sorted(
            {x for e in self._entries[direction] if kind in (None, e.kind) for x in e.extensions}
        )

    def candidates(self, direction: str, ext: str, kind: str | None = None) -> list[Entry]:
        """The records for extension ``ext`` (of ``kind`` when given), in precedence order."""
        return ranked(
            e for e in self._entries[direction] if ext in e.extensions and kind in (None, e.kind)
        )

    # -- looking inside files --------------------------------------------------------------
    @staticmethod
    def sniff_kind(path: Path, readers: list[Entry]) -> str | None:
        """The kind ``path`` holds according to the sniffers of ``readers`` (``Reader.sniff``),
        asked in precedence order, each distinct sniffer once: the first kind named that one
        of ``readers`` reads, or None. A sniffer that raises counts as not knowing."""
        kinds = {e.kind for e in readers}
        asked: set[int] = set()
        for entry in readers:
            sniff = getattr(entry.record, "sniff", None)
            if sniff is None or id(sniff) in asked:
                continue
            asked.add(id(sniff))
            try:
                kind = sniff(path)
            except Exception:  # unreadable or another kind of file: the reader will say so
                kind = None
            if kind in kinds:
                return kind
        return None

    def identify(self, path: Path) -> list[Entry]:
        """The readers whose magic bytes (``Reader.magic``) ``path`` starts with, in
        precedence order; [] when none does or the file cannot be read. ``path`` must be a
        regular file (the dispatcher checks before)."""
        if not any(getattr(e.record, "magic", ()) for e in self._entries["read"]):
            return []
        try:
            with open(path, "rb") as fh:
                head = fh.read(MAGIC_BYTES)
        except OSError:
            return []
        return ranked(
            e
            for e in self._entries["read"]
            if any(head.startswith(m) for m in getattr(e.record, "magic", ()) or ())
        )

    # -- precedence ------------------------------------------------------------------------
    def rows(self) -> list[dict[str, Any]]:
        """One dict per record (readers then writers): direction, name, kind, extensions,
        description, origin, builtin, priority, declines (has ``accepts``), and precedence
        among records of one extension and kind: ``shadowed_by`` (``{extension: name of the
        record that wins}``) and ``shadows`` (``{extension: [names]}``)."""
        rows = []
        for direction, entries in self._entries.items():
            groups: dict[tuple[str, str], list[Entry]] = {}
            for e in entries:
                for ext in e.extensions:
                    groups.setdefault((ext, e.kind), []).append(e)
            shadowed_by: dict[int, dict[str, str]] = {}
            shadows: dict[int, dict[str, list[str]]] = {}
            for (ext, _), group in groups.items():
                winner, *losers = ranked(group)
                for loser in losers:
                    shadowed_by.setdefault(loser.order, {})[ext] = winner.name
                    shadows.setdefault(winner.order, {}).setdefault(ext, []).append(loser.name)
            for e in entries:
                rows.append(
                    {
                        "direction": direction,
                        "name": e.name,
                        "kind": e.kind,
                        "extensions": list(e.extensions),
                        "description": e.record.description,
                        "origin": e.origin,
                        "builtin": e.builtin,
                        "priority": e.priority,
                        "declines": getattr(e.record, "accepts", None) is not None,
                        "shadowed_by": shadowed_by.get(e.order, {}),
                        "shadows": shadows.get(e.order, {}),
                    }
                )
        return rows


def ranked(entries: Iterable[Entry]) -> list[Entry]:
    """``entries`` in precedence order (see :meth:`Entry.precedence`)."""
    return sorted(entries, key=Entry.precedence)


def shadow_note(row: dict[str, Any]) -> str:
    """One line on a :meth:`FormatTable.rows` row's precedence, e.g. ``"shadowed by obj
    (.obj)"`` or ``"wins over obj (.obj)"``; empty when it shares no extension and kind."""
    parts = []
    if row["shadowed_by"]:
        by = ", ".join(f"{name} ({ext})" for ext, name in sorted(row["shadowed_by"].items()))
        later = "; gets only files the winner declines" if row["direction"] == "read" else ""
        parts.append(f"shadowed by {by}{later}")
    if row["shadows"]:
        parts.append(
            "wins over "
            + ", ".join(
                f"{'/'.join(names)} ({ext})" for ext, names in sorted(row["shadows"].items())
            )
        )
    return "; ".join(parts)
