"""Time two commits of drcpo side by side: ``bench_augment.py`` of each, in pairs, alternating.

The machine's speed drifts (on a shared 2-core machine by a third within minutes), so one run of
each commit says little; this runs ``--pairs`` pairs, the commits' order swapped every pair, and
prints each pair's ratio (``head`` over ``base``) per pipeline and stage, and their medians.
Each commit runs from its own git worktree, both under one temporary directory beside a link to
this checkout's ``../shared`` (when present), so that both read the same frames from the same
file system; the worktrees are removed afterwards. The database and index are built once, in
``--work``, and shared.

The last stdout line is one JSON object::

    {"base": rev, "head": rev, "pairs": n, "paper_ratio": median, "cda_ratio": median,
     "paper_ratio_range": [min, max], "base_ms": {pipeline: median}, "head_ms": {...},
     "stage_ratio": {stage: median}, ...}

Usage: ``python benchmarks/compare_revisions.py BASE [HEAD] [--pairs N] [--work DIR] [--quick]``
(``HEAD`` defaults to ``HEAD``: commit what you measure).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
PIPELINES = {"cda": "cda_ms", "paper": "drcpo_ms"}


def _git(*args: str) -> str:
    run = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"git {' '.join(args)} failed: {run.stderr.strip()}")
    return run.stdout.strip()


def _bench(tree: Path, work: Path, quick: bool) -> dict:
    """One ``bench_augment.py`` run of the commit checked out in ``tree``: its JSON."""
    env = {**os.environ, "PYTHONPATH": str(tree / "src")}
    script = [sys.executable, str(tree / "benchmarks" / "bench_augment.py")]
    run = subprocess.run(
        [*script, "--work", str(work), *(["--quick"] if quick else [])],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
    )
    if run.returncode != 0:
        raise SystemExit(f"bench_augment.py failed in {tree}:\n{run.stderr[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def _ratios(base: list[dict], head: list[dict]) -> dict:
    pipelines = {
        name: [h[key] / b[key] for b, h in zip(base, head, strict=True)]
        for name, key in PIPELINES.items()
    }
    stages = {}
    for stage in base[0]["stages_ms"]:
        pairs = [(b["stages_ms"], h["stages_ms"]) for b, h in zip(base, head, strict=True)]
        if all(stage in h and b[stage] > 0 for b, h in pairs):
            stages[stage] = statistics.median(h[stage] / b[stage] for b, h in pairs)
    return {"pipelines": pipelines, "stages": stages}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", help="the commit to compare against")
    parser.add_argument("head", nargs="?", default="HEAD", help="the commit measured (HEAD)")
    parser.add_argument("--pairs", type=int, help="runs of each commit (8, quick 2)")
    parser.add_argument("--quick", action="store_true", help="bench_augment.py --quick, 2 pairs")
    parser.add_argument("--work", type=Path, help="keep the database and index here")
    args = parser.parse_args(argv)
    if args.pairs is None:
        args.pairs = 2 if args.quick else 8
    if args.pairs < 1:
        parser.error("--pairs must be at least 1")
    revs = {side: _git("rev-parse", "--verify", f"{rev}^{{commit}}") for side, rev in
            (("base", args.base), ("head", args.head))}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="drcpo-compare-") as temp:
        root = Path(temp)
        if SHARED.is_dir():
            (root / "shared").symlink_to(SHARED)
        trees = {side: root / side for side in revs}
        work = args.work or root / "work"
        try:
            for side, rev in revs.items():
                _git("worktree", "add", "--detach", str(trees[side]), rev)
            runs: dict[str, list[dict]] = {"base": [], "head": []}
            for pair in range(args.pairs):
                order = ("base", "head") if pair % 2 == 0 else ("head", "base")
                for side in order:
                    runs[side].append(_bench(trees[side], work, args.quick))
                b, h = runs["base"][-1], runs["head"][-1]
                print(
                    f"pair {pair + 1}: paper {b['drcpo_ms']:.1f} -> {h['drcpo_ms']:.1f} ms, "
                    f"cda {b['cda_ms']:.1f} -> {h['cda_ms']:.1f} ms "
                    f"(load {h['load_average']:.2f})",
                    flush=True,
                )
        finally:
            for tree in trees.values():
                if tree.exists():
                    _git("worktree", "remove", "--force", str(tree))
    ratios = _ratios(runs["base"], runs["head"])
    result = {
        "base": revs["base"],
        "head": revs["head"],
        "pairs": args.pairs,
        "source": runs["head"][0]["source"],
        "paper_ratio": statistics.median(ratios["pipelines"]["paper"]),
        "cda_ratio": statistics.median(ratios["pipelines"]["cda"]),
        "paper_ratio_range": [min(ratios["pipelines"]["paper"]), max(ratios["pipelines"]["paper"])],
        "base_ms": {n: statistics.median(r[k] for r in runs["base"]) for n, k in PIPELINES.items()},
        "head_ms": {n: statistics.median(r[k] for r in runs["head"]) for n, k in PIPELINES.items()},
        "stage_ratio": ratios["stages"],
    }
    for stage, ratio in ratios["stages"].items():
        print(f"  paper {stage:<28} head / base {ratio:.3f}")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
