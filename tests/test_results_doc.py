"""docs/results.md and README.md's results table are what ``benchmarks/paper.py --markdown-only``
makes from the stored records (docs/results/*.json), not typed by hand."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from conftest import benchmark_script

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "results"


def _paper():
    return benchmark_script("paper")


def _generate(paper, records: Path, tmp_path: Path) -> tuple[str, str]:
    """(results.md, README.md) as paper.py writes them from ``records``."""
    readme = tmp_path / "README.md"
    shutil.copy(ROOT / "README.md", readme)
    out = tmp_path / "results.md"
    paper.write_markdown(paper.collect(records), "auto", out, readme, paper.generalization_records(records))
    return out.read_text(), readme.read_text()


def test_results_page_and_readme_table_are_regenerated_from_the_records(tmp_path):
    paper = _paper()
    results, readme = _generate(paper, RECORDS, tmp_path)
    assert results == (ROOT / "docs" / "results.md").read_text(), \
        "docs/results.md differs from the records: run python benchmarks/paper.py --markdown-only"
    assert readme == (ROOT / "README.md").read_text(), \
        "README.md's results table differs from the records: run python benchmarks/paper.py --markdown-only"
    table = readme.split(paper.README_BEGIN)[1].split(paper.README_END)[0]
    for data in paper.TARGET_SETS:
        assert f"\n| {data} | " in table


def test_the_table_follows_the_records(tmp_path):
    """Doubling ours' errors in the body set's shipped record doubles its ratios in both documents."""
    paper = _paper()
    records = tmp_path / "records"
    shutil.copytree(RECORDS, records)
    name = paper.shipped_records(paper.collect(RECORDS))["bodies"]
    summary = json.loads((records / f"{name}.json").read_text())
    bd = summary["results"]["bd"]
    before = paper.prediction_ratios(bd)
    for key in ("errors", "errors_aligned"):
        bd[key]["ours"] = {u: {h: 2 * v for h, v in per_h.items()} for u, per_h in bd[key]["ours"].items()}
    (records / f"{name}.json").write_text(json.dumps(summary))
    results, readme = _generate(paper, records, tmp_path)
    row = f"| bodies | 7000 of 7000 | {2 * min(before):.2f}-{2 * max(before):.2f} "
    assert row in results and row in readme


def test_the_generalisation_table_follows_its_records(tmp_path):
    """Doubling ours' u1 h10 error in a generalisation record doubles its ratio in results.md."""
    paper = _paper()
    records = tmp_path / "records"
    shutil.copytree(RECORDS, records)
    files = paper.generalization_records(records)
    assert files, "docs/results/generalize/ holds no records"
    rec = json.loads(files[0].read_text())
    block = rec["blocks"][0]
    ours = block["prediction"]["u1"]["ours"]["centroid"]
    best = min(block["prediction"]["u1"][m]["centroid"]["10"] for m in block["prediction"]["u1"] if m != "ours")
    ours["10"] = 2 * ours["10"]
    files[0].write_text(json.dumps(rec))
    results, _ = _generate(paper, records, tmp_path)
    seq = block["sequence"].replace("\\", "/").split("/")[-1]
    row = next(line for line in results.splitlines() if line.startswith(f"| {rec['set']} ") and f" | {seq} | " in line)
    assert row.split(" | ")[5] == f"{ours['10'] / best:.2f}"


def _generalize():
    return benchmark_script("generalize")


def _scale_ours(rec: dict, factor: float) -> None:
    """Ours' prediction error set to ``factor`` x the best baseline's in every cell of ``rec``."""
    for block in rec["blocks"]:
        for per_u in block["prediction"].values():
            for key, per_h in per_u["ours"].items():
                for h in per_h:
                    per_h[h] = factor * min(per_u[m][key][h] for m in per_u if m != "ours")


def test_the_targets_table_marks_each_missed_target_with_the_cell_that_misses_it():
    generalize = _generalize()
    rec = json.loads((RECORDS / "generalize" / "bodies-at-end.json").read_text())
    _scale_ours(rec, 0.4)
    shown, novel, *_, subject = generalize.record_targets(rec)
    assert shown == "0.40 met" and novel == "0.40 met" and subject.startswith("0.40 met; ")
    _scale_ours(rec, 1.6)
    shown, novel, *_, subject = generalize.record_targets(rec)
    assert shown.startswith("**1.60** (male_slim_") and novel.startswith("**1.60** (") and "_shake_arms " in novel
    assert subject.startswith("**1.60** (male_slim_") and " h15" in subject.split(";")[0]
    for block in rec["blocks"]:
        block["motion_50"] = 1.0
    block["motion_50"] = 0.5
    assert generalize.record_targets(rec)[4] == f"**0.50** ({block['sequence'].rsplit(':', 1)[-1]})"
    block["motion_50"] = 0.75  # within 30% of the truth's: 0.7-1.3, as the column says
    assert generalize.record_targets(rec)[4] == "0.75-1.00 met"


def test_a_record_scored_with_another_pace_trust_or_line_says_so(tmp_path):
    generalize = _generalize()
    rec = json.loads((RECORDS / "generalize" / "bodies-at-end.json").read_text())
    assert rec["pace"] == generalize.scored_pace() and rec["trust"] == generalize.TRUST
    assert rec["line"] == generalize.LINE
    assert generalize.record_label(rec) == "bodies, 2000 it"
    del rec["pace"]  # scored before records named their pace
    assert generalize.record_label(rec) == "bodies, 2000 it, pace warm-up"
    del rec["trust"]  # and their completion's trust
    assert generalize.record_label(rec) == "bodies, 2000 it, pace warm-up, trust warm-up"
    del rec["line"]  # and the line completion draws toward
    old = "bodies, 2000 it, pace warm-up, trust warm-up, straight line"
    assert generalize.record_label(rec) == old
    path = tmp_path / "old.json"
    path.write_text(json.dumps(rec))
    assert f"| bodies unseen sequence, {old.removeprefix('bodies, ')} |" in generalize.table([str(path)])
    rec["train"]["consistency"] = "temporal"  # trained before the smallest-turn walk
    assert generalize.record_label(rec) == old + ", temporal logs"
    rec["train"]["holdout"] = 0.2  # a single capture: the same features under both walks
    assert generalize.record_label(rec) == old


def test_a_capture_held_out_by_another_fraction_is_named_for_it():
    generalize = _generalize()
    assert generalize.capture_name("/data/pcow.npz", generalize.HOLDOUT) == "pcow"
    assert generalize.capture_name("/data/pcow.npz", 0.1) == "pcow-holdout0.1"
    assert generalize.capture_name("crane.npz", 0.05) == "crane-holdout0.05"


def test_the_targets_table_names_a_block_inside_a_capture(tmp_path):
    generalize = _generalize()
    rec = json.loads((RECORDS / "generalize" / "pcow-at-end.json").read_text())
    path = tmp_path / "pcow.json"
    path.write_text(json.dumps(rec))
    assert "| pcow, 2000 it |" in generalize.targets_table([str(path)])
    rec["holdout_at"] = "0.5"
    path.write_text(json.dumps(rec))
    assert "| pcow @ 0.5, 2000 it |" in generalize.targets_table([str(path)])


def test_controlled_run_changes_are_checked_as_config_lines():
    import pytest

    generalize = _generalize()
    assert generalize.recipe_changes(["speed_augment=1.5", "input_norm=false", "ema_decay=none"]) == \
        {"speed_augment": 1.5, "input_norm": False, "ema_decay": None}
    with pytest.raises(SystemExit, match="speed: not a training option"):
        generalize.recipe_changes(["speed=2"])
    with pytest.raises(SystemExit, match="speed_augment: 0.5"):
        generalize.recipe_changes(["speed_augment=0.5"])
