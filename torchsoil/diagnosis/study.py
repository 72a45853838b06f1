"""Confusion-table study of the diagnosis on seeded synthetic drives with known truth
(the cases: `study_cases.STUDY_CASES`)."""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

from torchsoil.diagnosis.run import diagnose
from torchsoil.settings import Settings
from torchsoil.synth.scenario import make_terrain_pair
from torchsoil.terrain import TerrainPair


def run_study(cases, out: Path, settings: Settings | None = None) -> str:
    """Diagnose every (name, scenario, seed, verdict, id) case; append results to
    out/cases.jsonl (cases already there are skipped) and return the confusion table (markdown)."""
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    log = out / "cases.jsonl"
    done = {json.loads(line)["case"]: json.loads(line) for line in log.read_text().splitlines()} if log.exists() else {}
    settings = settings or Settings()
    for name, scn, seed, want_verdict, want_id in tqdm(cases, desc="study", unit="case"):
        if name in done:
            continue
        t0 = time.perf_counter()
        pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=seed))
        s = diagnose(pair, settings.diagnosis, settings.estimator, settings.sim).summary
        rec = {"case": name, "seed": seed, "want": want_verdict, "want_id": want_id, "verdict": s["verdict"],
               "id": s["missing_physics"], "where": s["where"], "parameters": s["extension_parameters"],
               "cost_before": s["cost_before"], "cost_after": s["cost_after"],
               "correct": s["verdict"] == want_verdict and s["missing_physics"] == want_id,
               "seconds": time.perf_counter() - t0}
        done[name] = rec
        with log.open("a") as f:
            f.write(json.dumps(rec) + "\n")
    table = confusion(list(done.values()))
    (out / "confusion.md").write_text(table)
    return table


def confusion(records: list[dict]) -> str:
    """Markdown: per expected answer, how often each verdict came out, and the case list."""
    def label(verdict, eid):
        return eid if verdict == "missing_physics" else verdict

    counts: dict[str, Counter] = {}
    for r in records:
        counts.setdefault(label(r["want"], r["want_id"]), Counter())[label(r["verdict"], r["id"])] += 1
    cols = sorted({c for v in counts.values() for c in v})
    lines = ["| truth \\ verdict | " + " | ".join(cols) + " | right |", "|" + " --- |" * (len(cols) + 2)]
    for t, c in sorted(counts.items()):
        lines.append(f"| {t} | " + " | ".join(str(c.get(k, 0)) for k in cols) + f" | {c.get(t, 0)}/{sum(c.values())} |")
    right = sum(r["correct"] for r in records)
    lines += ["", f"right: {right}/{len(records)}", "",
              "| case | verdict | parameters | prediction before -> after [mm] |", "| --- | --- | --- | --- |"]
    for r in records:
        lines.append(f"| {r['case']} | {label(r['verdict'], r['id'])} | {r['parameters']} | "
                     f"{1e3 * r['cost_before']['prediction']:.3f} -> {1e3 * r['cost_after']['prediction']:.3f} |")
    return "\n".join(lines) + "\n"
