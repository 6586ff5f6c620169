"""pis3r against its peers, pair by pair: the number issue 11 drives to zero.

For every case, pis3r's extension PSNR is compared with the best peer's on that case; a
pair where pis3r is more than ``BEHIND_DB`` below the best peer counts against it. Rows
are the evaluation's result rows (one per case x method: ``case``, ``method``,
``parallax_class`` and the score keys; see :mod:`pis3r.eval.runner`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pis3r.eval.cases import PARALLAX_CLASSES, UNKNOWN_CLASS

SUBJECT = "pis3r"
# pis3r more than this many dB below the best peer on a pair is a pair it loses.
BEHIND_DB = 1.0
PSNR_KEY, LPIPS_KEY = "bar_psnr", "bar_lpips"
ALL_CLASSES = "all"


@dataclass(frozen=True)
class PairMargin:
    """One case: pis3r's extension PSNR (dB), the best peer on it and that peer's PSNR.
    ``margin`` = pis3r − best peer (dB): ``-inf`` when pis3r filled nothing of the extension
    while a peer did; NaN when no peer scored the case."""

    case: str
    parallax_class: str
    subject_psnr: float
    best_peer: str | None
    best_peer_psnr: float

    @property
    def margin(self) -> float:
        if self.best_peer is None:
            return math.nan
        if math.isnan(self.subject_psnr):
            return -math.inf
        return self.subject_psnr - self.best_peer_psnr

    @property
    def behind(self) -> bool:
        """pis3r is more than ``BEHIND_DB`` below the best peer (NaN margin: not compared)."""
        return self.margin < -BEHIND_DB


def _score(row: dict, key: str) -> float:
    value = row.get(key)
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def pair_margins(rows: list[dict], subject: str = SUBJECT) -> list[PairMargin]:
    """One :class:`PairMargin` per case that ``subject`` ran on, in case order; the best
    peer is the other method with the highest finite ``PSNR_KEY`` on the case."""
    by_case: dict[str, dict[str, dict]] = {}
    for row in rows:
        by_case.setdefault(row["case"], {})[row["method"]] = row
    margins = []
    for case in sorted(by_case):
        methods = by_case[case]
        if subject not in methods:
            continue
        peers = {m: _score(r, PSNR_KEY) for m, r in methods.items() if m != subject}
        finite = {m: v for m, v in peers.items() if math.isfinite(v)}
        best = max(finite, key=finite.get) if finite else None
        margins.append(PairMargin(case, methods[subject]["parallax_class"], _score(methods[subject], PSNR_KEY),
                                  best, finite[best] if best else math.nan))
    return margins


def behind_counts(margins: list[PairMargin]) -> dict[str, tuple[int, int]]:
    """``{class: (pairs where pis3r is behind, pairs compared)}`` for each parallax class
    present, in ``PARALLAX_CLASSES`` order, and ``ALL_CLASSES``."""
    compared = [m for m in margins if m.best_peer is not None]
    present = {m.parallax_class for m in compared}
    counts = {}
    for name in (*[c for c in (*PARALLAX_CLASSES, UNKNOWN_CLASS) if c in present], ALL_CLASSES):
        group = [m for m in compared if name in (ALL_CLASSES, m.parallax_class)]
        counts[name] = (sum(m.behind for m in group), len(group))
    return counts


def margin_fields(margins: list[PairMargin]) -> dict[str, dict]:
    """``{case: fields}`` to add to the subject's result row (report.csv) of every case a
    peer scored: the best peer, its PSNR, the margin and whether pis3r is behind."""
    return {m.case: {"best_peer": m.best_peer, "best_peer_psnr": m.best_peer_psnr,
                     "margin_db": m.margin, "behind_best_peer": m.behind} for m in margins if m.best_peer}


def _fmt(value: float, fmt: str) -> str:
    return "–" if math.isnan(value) else fmt.format(value)


def _method_cell(row: dict | None) -> str:
    """``PSNR / LPIPS`` of one method on one case, with what went wrong, if anything."""
    if row is None:
        return "–"
    text = f"{_fmt(_score(row, PSNR_KEY), '{:.2f}')} / {_fmt(_score(row, LPIPS_KEY), '{:.3f}')}"
    if row.get("status") == "failed":
        return text + " (failed)"
    if row.get("registered") is False:
        return text + " (unregistered)"
    return text


def per_pair_table(rows: list[dict], subject: str = SUBJECT) -> list[str]:
    """Markdown: one line per case, each method's extension PSNR (dB) / LPIPS, the best peer,
    pis3r − best peer (dB), and whether pis3r is more than ``BEHIND_DB`` below it; then
    the count of such pairs per parallax class. Empty without the subject or a peer."""
    margins = [m for m in pair_margins(rows, subject) if m.best_peer is not None]
    if not margins:
        return []
    methods = list(dict.fromkeys(r["method"] for r in rows if r["method"] != subject))
    cells = {(r["case"], r["method"]): r for r in rows}
    lines = [f"| case | class | {subject} | " + " | ".join(methods) + f" | best peer | {subject} − best (dB) | "
             f"> {BEHIND_DB:g} dB below |",
             "|---|---|" + "---:|" * (len(methods) + 1) + "---|---:|---|"]
    for m in margins:
        row_cells = [_method_cell(cells.get((m.case, name))) for name in (subject, *methods)]
        lines.append(f"| {m.case} | {m.parallax_class} | " + " | ".join(row_cells)
                     + f" | {m.best_peer} | {m.margin:+.2f} | {'yes' if m.behind else ''} |")
    lines += ["", f"| class | pairs | {subject} > {BEHIND_DB:g} dB below the best peer |", "|---|---:|---:|"]
    lines += [f"| {name} | {total} | {behind} |" for name, (behind, total) in behind_counts(margins).items()]
    return lines
