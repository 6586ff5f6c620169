"""pis3r against the best peer, per pair, and the count of pairs it loses by more than 1 dB."""

from __future__ import annotations

import csv
import math

from pis3r.eval.margins import behind_counts, pair_margins, per_pair_table
from pis3r.eval.report import render_markdown, write_csv


def row(case, parallax_class, method, psnr, lpips=0.3, **extra):
    return {"case": case, "dataset": "hand", "kind": "pair", "parallax_class": parallax_class, "method": method,
            "status": "ok", "seconds": 1.0, "registered": True, "bar_psnr": psnr, "bar_lpips": lpips,
            "ext_psnr": psnr, **extra}


ROWS = [
    # pis3r 1.5 dB below the best of two peers: behind.
    row("a", "large", "pis3r", 16.0), row("a", "large", "apap", 17.5), row("a", "large", "opencv", 15.0),
    # 0.8 dB below: within the tolerance.
    row("b", "large", "pis3r", 16.0), row("b", "large", "apap", 16.8),
    # Exactly 1 dB below is not more than 1 dB below.
    row("c", "large", "pis3r", 15.0), row("c", "large", "apap", 16.0, registered=False),
    # pis3r filled nothing of the extension where a peer did: behind.
    row("d", "slight", "pis3r", math.nan), row("d", "slight", "apap", 12.0),
    # The peers failed (an empty extension's score) or filled nothing: pis3r ahead.
    row("e", "slight", "pis3r", 20.0), row("e", "slight", "apap", 9.0, status="failed", registered=False),
    row("e", "slight", "opencv", math.nan),
    # No peer scored these: not compared.
    row("f", "rotation", "pis3r", 30.0), row("g", "rotation", "pis3r", 25.0), row("g", "rotation", "apap", math.nan),
]


def test_margin_to_the_best_peer_per_pair():
    margins = {m.case: m for m in pair_margins(ROWS)}
    assert [m.case for m in margins.values()] == ["a", "b", "c", "d", "e", "f", "g"]
    assert margins["a"].best_peer == "apap" and math.isclose(margins["a"].margin, -1.5)
    assert margins["d"].margin == -math.inf
    assert margins["e"].best_peer == "apap" and math.isclose(margins["e"].margin, 11.0)
    assert margins["f"].best_peer is None and margins["g"].best_peer is None
    assert [c for c, m in margins.items() if m.behind] == ["a", "d"]


def test_count_of_pairs_more_than_1_db_below_the_best_peer_per_class():
    assert behind_counts(pair_margins(ROWS)) == {"slight": (1, 2), "large": (1, 3), "all": (2, 5)}


def test_per_pair_table_lists_each_method_and_the_counts():
    lines = per_pair_table(ROWS)
    assert lines[0] == "| case | class | pis3r | apap | opencv | best peer | pis3r − best (dB) | > 1 dB below |"
    assert "| a | large | 16.00 / 0.300 | 17.50 / 0.300 | 15.00 / 0.300 | apap | -1.50 | yes |" in lines
    assert "| c | large | 15.00 / 0.300 | 16.00 / 0.300 (unregistered) | – | apap | -1.00 |  |" in lines
    assert "| e | slight | 20.00 / 0.300 | 9.00 / 0.300 (failed) | – / 0.300 | apap | +11.00 |  |" in lines
    assert not any(line.startswith(("| f |", "| g |")) for line in lines)
    assert lines[-3:] == ["| slight | 2 | 1 |", "| large | 3 | 1 |", "| all | 5 | 2 |"]
    assert per_pair_table([r for r in ROWS if r["method"] == "pis3r"]) == []


def test_report_shows_the_table_and_the_csv_carries_the_margins(tmp_path):
    assert "## pis3r against the best peer, per pair" in render_markdown(ROWS, "hand")
    write_csv(ROWS, tmp_path / "report.csv")
    lines = {(r["case"], r["method"]): r for r in csv.DictReader((tmp_path / "report.csv").open())}
    assert lines[("a", "pis3r")]["best_peer"] == "apap" and float(lines[("a", "pis3r")]["margin_db"]) == -1.5
    assert lines[("a", "pis3r")]["behind_best_peer"] == "True" and lines[("b", "pis3r")]["behind_best_peer"] == "False"
    assert lines[("a", "apap")]["margin_db"] == "" and lines[("f", "pis3r")]["margin_db"] == ""
