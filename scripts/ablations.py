"""Run the ablations behind docs/results.md and write them as one JSON file.

    PYTHONPATH=. python scripts/ablations.py [--quick] [--jobs N] [--seed S] [--out DIR]

See supramodal/experiments/ablations.py for what each one varies.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from supramodal.experiments.ablations import plans
from supramodal.experiments.common import progress_to_stderr
from supramodal.experiments.runner import run_plans


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--jobs", type=int)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/ablations")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    results = run_plans(plans(quick=args.quick), jobs=args.jobs, seed=args.seed, progress=progress_to_stderr)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablations.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {out / 'ablations.json'} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
