"""Turns evaluation rows into ``report.md``, ``report.csv``, ``quality_vs_parallax.png`` and
one contact sheet per case.

A row is one case x method (see :mod:`pis3r.eval.runner`); rows whose ``method`` is
``runner.CASE_TASK`` describe the case itself (estimated parallax level).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.eval.cases import PARALLAX_CLASSES, UNKNOWN_CLASS
from pis3r.eval.margins import BEHIND_DB, SUBJECT, margin_fields, pair_margins, per_pair_table
from pis3r.eval.runner import CASE_TASK, preview_path
from pis3r.io import read_image, to_uint8, write_bytes, write_png

# Direction in which a column is better; the best value of a column is printed bold.
HIGHER, LOWER = "max", "min"


@dataclass(frozen=True)
class Column:
    """One table column: ``title``, the row ``key`` summarised, which ``rows`` (``all`` or
    ``registered``), ``better`` (``HIGHER`` | ``LOWER``), a number format and the statistic
    over rows (``mean``, or ``median`` where single cases can be off by orders of magnitude)."""

    title: str
    key: str
    better: str
    rows: str = "all"
    fmt: str = "{:.3f}"
    stat: str = "mean"


TABLE3 = (
    Column("PSNR ↑", "valid_psnr", HIGHER),
    Column("SSIM ↑", "valid_ssim", HIGHER),
    Column("LPIPS ↓", "valid_lpips", LOWER),
    Column("RSR ↑", "registered", HIGHER, fmt="{:.1%}"),
    Column("PSNR ↑ (reg.)", "valid_psnr", HIGHER, "registered"),
    Column("SSIM ↑ (reg.)", "valid_ssim", HIGHER, "registered"),
    Column("LPIPS ↓ (reg.)", "valid_lpips", LOWER, "registered"),
)
EXTENSION = (
    Column("PSNR ↑", "bar_psnr", HIGHER),
    Column("SSIM ↑", "bar_ssim", HIGHER),
    Column("LPIPS ↓", "bar_lpips", LOWER),
    Column("coverage ↑", "coverage", HIGHER, fmt="{:.1%}"),
    Column("strict PSNR ↑", "ext_psnr", HIGHER),
    Column("strict SSIM ↑", "ext_ssim", HIGHER),
    Column("strict LPIPS ↓", "ext_lpips", LOWER),
    Column("RSR ↑", "registered", HIGHER, fmt="{:.1%}"),
    Column("s / pair ↓", "seconds", LOWER, fmt="{:.1f}"),
)
EXACT = tuple(Column(c.title, f"exact_{c.key}", c.better, fmt=c.fmt) for c in EXTENSION[:7]) + (
    Column("valid PSNR ↑", "exact_valid_psnr", HIGHER),
)
GEOMETRY = (
    Column("Sampson d² ↓ (px², median of cases)", "sampson_median", LOWER, stat="median"),
    Column("Sampson d² ↓ (px², mean of cases)", "sampson_median", LOWER),
    Column("matches (median)", "sampson_matches", HIGHER, fmt="{:.0f}", stat="median"),
    Column("rotation error ↓ (°, median)", "rotation_error_deg", LOWER, fmt="{:.2f}", stat="median"),
    Column("translation error ↓ (°, median)", "translation_error_deg", LOWER, fmt="{:.2f}", stat="median"),
)
NO_REFERENCE = (
    Column("PIQE ↓", "piqe", LOWER, fmt="{:.2f}"),
    Column("NIQE ↓", "niqe", LOWER),
    Column("failures ↓", "failed", LOWER, fmt="{:.0f}"),
    Column("s / pair ↓", "seconds", LOWER, fmt="{:.1f}"),
)


def mean_of(rows: list[dict], column: Column) -> float:
    """``column.stat`` (mean or median) of ``column.key`` over ``rows`` (only registered ones
    for ``rows="registered"``), ignoring missing and NaN values; booleans count as 0/1;
    ``failed`` counts failures. NaN when nothing is left."""
    if column.rows == "registered":
        rows = [r for r in rows if r.get("registered")]
    if column.key == "failed":
        return float(sum(r.get("status") == "failed" for r in rows))
    values = [float(r[column.key]) for r in rows if isinstance(r.get(column.key), (bool, int, float))]
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return math.nan
    return float(np.median(values) if column.stat == "median" else np.mean(values))


def markdown_table(groups: dict[str, list[dict]], columns: tuple[Column, ...], label: str = "Method") -> list[str]:
    """A markdown table with one line per group (``{name: rows}``) and the best of each column bold."""
    means = {name: [mean_of(rows, c) for c in columns] for name, rows in groups.items()}
    best = []
    for i, column in enumerate(columns):
        finite = [m[i] for m in means.values() if math.isfinite(m[i])]
        best.append((max if column.better == HIGHER else min)(finite) if len(finite) > 1 else None)
    lines = [f"| {label} | n | " + " | ".join(c.title for c in columns) + " |",
             "|---|---:|" + "---:|" * len(columns)]
    for name, values in means.items():
        cells = []
        for value, column, top in zip(values, columns, best):
            text = "–" if math.isnan(value) else column.fmt.format(value)
            cells.append(f"**{text}**" if top is not None and value == top else text)
        lines.append(f"| {name} | {len(groups[name])} | " + " | ".join(cells) + " |")
    return lines


def _by_method(rows: list[dict], methods: list[str]) -> dict[str, list[dict]]:
    return {m: [r for r in rows if r["method"] == m] for m in methods}


def _classes(rows: list[dict]) -> list[str]:
    present = {r["parallax_class"] for r in rows}
    return [c for c in (*PARALLAX_CLASSES, UNKNOWN_CLASS) if c in present]


def _methods(rows: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["method"] for r in rows if r["method"] != CASE_TASK))


def render_markdown(rows: list[dict], title: str) -> str:
    """The whole ``report.md`` for evaluation ``rows``."""
    method_rows = [r for r in rows if r["method"] != CASE_TASK]
    methods = _methods(rows)
    ground_truth = any("ext_psnr" in r for r in method_rows)
    out = [f"# {title}", ""]
    cases = sorted({r["case"] for r in method_rows})
    out += [f"{len(cases)} cases, methods: {', '.join(methods)}.", ""]
    if ground_truth:
        out += [
            "Protocol (paper, Sec. Experiments): the reference is padded to the GT size at its offset, each "
            "method's canvas is registered to it with one SIFT + MAGSAC homography (the same for every method) "
            "and scored on its valid pixels. A crash, timeout, refusal or failed registration is a registration "
            "failure (RSR) and is scored as an empty result (the padded reference, black elsewhere). "
            "Extension tables: GT outside the reference only. PSNR / SSIM / LPIPS there on the pixels the "
            "method filled, a failure scored as an empty extension (issue 2's bar); *coverage*: share of "
            "the extension filled; *strict*: the whole extension with unfilled pixels black.",
            "",
        ]
    for dataset in sorted({r["dataset"] for r in method_rows}):
        subset = [r for r in method_rows if r["dataset"] == dataset]
        groups = [("all pairs", subset)]
        groups += [(c, [r for r in subset if r["parallax_class"] == c]) for c in _classes(subset)]
        if ground_truth:
            out += [f"## {dataset}: paper's Table 3 layout (registered, valid pixels)", ""]
            for name, group in groups:
                out += [f"### {name}", "", *markdown_table(_by_method(group, methods), TABLE3), ""]
            out += [f"## {dataset}: extension region (GT outside the reference)", ""]
            for name, group in groups:
                out += [f"### {name}", "", *markdown_table(_by_method(group, methods), EXTENSION), ""]
            exact = [m for m in methods if any("exact_ext_psnr" in r for r in subset if r["method"] == m)]
            if exact:
                out += [f"## {dataset}: exact offset, no registration ({', '.join(exact)})", ""]
                for name, group in groups:
                    out += [f"### {name}", "", *markdown_table(_by_method(group, exact), EXACT), ""]
            geometric = [m for m in methods if any("sampson_median" in r for r in subset if r["method"] == m)]
            if geometric:
                out += [f"## {dataset}: geometry (cases with GT cameras)", "",
                        "Sampson epipolar error (paper eq. 11, per case the median over matches) between the two "
                        "canvases of a pair (one per camera), against the GT fundamental matrix of the canvas "
                        "cameras; relative-pose error of the reconstruction. Each method over the cases it "
                        "stitched (n).", ""]
                with_cameras = [r for r in subset if "sampson_median" in r]
                out += [*markdown_table(_by_method(with_cameras, geometric), GEOMETRY), ""]
        else:
            out += [f"## {dataset}: no-reference quality of the stitched canvases", ""]
            for name, group in groups:
                out += [f"### {name}", "", *markdown_table(_by_method(group, methods), NO_REFERENCE), ""]
    versus_peers = per_pair_table(method_rows) if ground_truth else []
    if versus_peers:
        out += [f"## {SUBJECT} against the best peer, per pair", "",
                f"Extension PSNR (dB) / LPIPS of each method (the registered protocol above, a failure scored as "
                f"an empty extension); the best peer is the other method with the highest PSNR on the pair; "
                f"the pairs where {SUBJECT} is more than {BEHIND_DB:g} dB below it are counted per class.", "",
                *versus_peers, ""]
    out += ["## Wall time per method", "", "Seconds of the method itself per pair (its child process; "
            "failed runs excluded).", "", *_timing_table(method_rows, methods), ""]
    out += ["## Per case", "", *_per_case_table(method_rows, ground_truth), ""]
    return "\n".join(out)


def _timing_table(rows: list[dict], methods: list[str]) -> list[str]:
    lines = ["| Method | runs | failed | mean s | median s | max s | total s |", "|---|---:|---:|---:|---:|---:|---:|"]
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        seconds = np.array([r["seconds"] for r in mine if r.get("status") == "ok"], float)
        stats = [seconds.mean(), np.median(seconds), seconds.max(), seconds.sum()] if len(seconds) else [math.nan] * 4
        failed = sum(r.get("status") == "failed" for r in mine)
        lines.append(f"| {method} | {len(mine)} | {failed} | " + " | ".join(_cell(v, "{:.1f}") for v in stats) + " |")
    return lines


def _per_case_table(rows: list[dict], ground_truth: bool) -> list[str]:
    if ground_truth:
        keys = ("bar_psnr", "bar_ssim", "bar_lpips", "coverage", "ext_psnr", "valid_psnr")
    else:
        keys = ("piqe", "niqe")
    flags = ("registered",) if ground_truth else ()
    lines = ["| case | class | method | " + " | ".join(keys + flags) + " | s | note |",
             "|---|---|---|" + "---:|" * len(keys) + "---|" * len(flags) + "---:|---|"]
    for r in rows:
        cells = [_cell(r.get(k)) for k in keys] + ["yes" if r.get(k) else "no" for k in flags]
        note = r.get("failure") or r.get("reg_reason") or ""
        lines.append(f"| {r['case']} | {r['parallax_class']} | {r['method']} | " + " | ".join(cells)
                     + f" | {_cell(r.get('seconds'), '{:.1f}')} | {note} |")
    return lines


def _cell(value, fmt: str = "{:.3f}") -> str:
    if not isinstance(value, (int, float)) or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return fmt.format(value)


def write_csv(rows: list[dict], path: Path) -> None:
    """``report.csv``: one line per case x method, every key any row has; pis3r's lines also
    carry the best peer of the pair, its PSNR and pis3r's margin to it."""
    method_rows = [r for r in rows if r["method"] != CASE_TASK]
    margins = margin_fields(pair_margins(method_rows))
    method_rows = [{**r, **margins.get(r["case"], {})} if r["method"] == SUBJECT else r for r in method_rows]
    keys = list(dict.fromkeys(k for r in method_rows for k in r))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=keys, restval="")
    writer.writeheader()
    writer.writerows(method_rows)
    write_bytes(path, buffer.getvalue().encode())


def plot_level(case_row: dict) -> float:
    """x position of a case in the parallax plot: P_L in % of the diagonal; a synthetic case's
    exact level (same definition) when it has one, else the one estimated from its inputs."""
    if case_row.get("kind") == "synth" and math.isfinite(case_row.get("parallax_level", math.nan)):
        return float(case_row["parallax_level"])
    return float(case_row.get("estimated_parallax_level", math.nan))


def plot_quality_vs_parallax(rows: list[dict], path: Path) -> None:
    """``quality_vs_parallax.png``: extension PSNR / SSIM / LPIPS (issue 2's bar: filled
    pixels, failures as an empty extension) against the parallax level, one colour per
    method: each case a dot, the mean per level bin a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = {r["case"]: plot_level(r) for r in rows if r["method"] == CASE_TASK}
    finite_levels = [v for v in levels.values() if math.isfinite(v)]
    edges = np.quantile(finite_levels, np.linspace(0, 1, 6)) if finite_levels else np.array([0.0, 1.0])
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for key, name, axis in zip(("bar_psnr", "bar_ssim", "bar_lpips"), ("PSNR (dB)", "SSIM", "LPIPS"), axes):
        for index, method in enumerate(_methods(rows)):
            points = np.array([(levels.get(r["case"], math.nan), r.get(key, math.nan)) for r in rows
                               if r["method"] == method], float).reshape(-1, 2)
            points = points[np.isfinite(points).all(axis=1)]
            colour = f"C{index}"
            axis.scatter(points[:, 0], points[:, 1], s=12, alpha=0.5, color=colour)
            bins = np.clip(np.searchsorted(edges, points[:, 0], side="right") - 1, 0, len(edges) - 2)
            centres = [(points[bins == b, 0].mean(), points[bins == b, 1].mean()) for b in range(len(edges) - 1)
                       if (bins == b).any()]
            if centres:
                axis.plot(*np.array(centres).T, "-o", color=colour, label=method, markersize=4)
        # Levels span 0 (rotation) to far beyond 100 % (wide baselines): linear near 0, log beyond.
        axis.set_xscale("symlog", linthresh=1.0)
        axis.set_xlabel("parallax level P_L (% of the image diagonal)")
        axis.set_ylabel(f"extension {name}")
        axis.grid(alpha=0.3)
    axes[0].legend()
    figure.suptitle("Quality of the extension (GT outside the reference; a failure = an empty extension) "
                    "against parallax")
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    write_bytes(path, buffer.getvalue())


def contact_sheet(outdir: Path, case_name: str, methods: list[str]) -> np.ndarray | None:
    """``(H, W, 3)`` uint8 sheet for one case: GT | reference | target | each method (a grey tile
    where a method produced nothing), each tile labelled. ``None`` without previews."""
    names = [("GT", "gt.png"), ("reference", "reference.png"), ("target", "target.png")]
    names += [(m, f"{m}.png") for m in methods]
    tiles = []
    for label, file_name in names:
        path = preview_path(outdir, case_name, file_name)
        tiles.append((label, read_image(path).pixels if path.is_file() else None))
    if tiles[0][1] is None:
        return None
    height = max(t.shape[0] for _, t in tiles if t is not None)
    width = max(t.shape[1] for _, t in tiles if t is not None)
    row = []
    for label, tile in tiles:
        canvas = np.full((height + 24, width, 3), 128 if tile is None else 255, np.uint8)
        if tile is not None:
            canvas[24 : 24 + tile.shape[0], : tile.shape[1]] = to_uint8(tile)
        cv2.putText(canvas, label if tile is not None else f"{label}: failed", (4, 17),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        row.append(canvas)
    return np.concatenate(row, axis=1)


def write_report(rows: list[dict], outdir: str | Path, title: str = "pis3r evaluation") -> list[Path]:
    """Write ``report.md``, ``report.csv``, ``quality_vs_parallax.png`` (with ground truth)
    and ``contact/<case>.png`` into ``outdir``; returns the paths written."""
    outdir = Path(outdir)
    written = [outdir / "report.md", outdir / "report.csv"]
    write_bytes(written[0], (render_markdown(rows, title) + "\n").encode())
    write_csv(rows, written[1])
    if any("bar_psnr" in r for r in rows):
        written.append(outdir / "quality_vs_parallax.png")
        plot_quality_vs_parallax(rows, written[-1])
    methods = _methods(rows)
    for case_name in sorted({r["case"] for r in rows}):
        sheet = contact_sheet(outdir, case_name, methods)
        if sheet is not None:
            written.append(outdir / "contact" / f"{case_name}.png")
            write_png(written[-1], sheet)
    return written
