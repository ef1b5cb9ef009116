#!/usr/bin/env python
"""Train the learned labeller and write ``ucad_cl/models/labeller.onnx`` + ``labeller.json``.

    .venv/bin/python -m pip install -e ".[train]"         # scikit-learn, onnx
    .venv/bin/python scripts/train_labeller.py            # the shipped model (minutes, 2 cores)
    .venv/bin/python scripts/train_labeller.py --vehicles 4 --test-vehicles 2 --max-iter 5 \
        --no-real --out /tmp/lab/labeller.onnx            # a smoke run (seconds)

Deterministic: the same arguments give the same model bytes (``--members`` models, member k on
the generated vehicles of seed + k from seeded recipes, real models read in manifest order,
trees fitted with fixed seeds and no early stopping). The data recipe
(``ucad_cl.labeller_train``), the seed and the metrics reached (train accuracy, accuracy on
generated vehicles of another seed never used for training) are written to the JSON beside the
model. Real models (``--real``, default ../shared/data/vehicles when present) add their
materials with names kept and hidden; ``bench/parts.py`` scores the real models
leave-one-model-out (it retrains without the scored model for each fold).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[2:]))
    from ucad_cl.labeller_train import DEFAULT_SEED, DEFAULT_VEHICLES, MEMBERS

    ap.add_argument("--vehicles", type=int, default=DEFAULT_VEHICLES,
                    help=f"generated training vehicles per member (default {DEFAULT_VEHICLES})")
    ap.add_argument("--test-vehicles", type=int, default=100,
                    help="generated vehicles of another seed to score (never trained on)")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED,
                    help="recipe seed: member k trains on the generated vehicles of seed + k")
    ap.add_argument("--members", type=int, default=MEMBERS,
                    help=f"models averaged, each on its own generated draw (default {MEMBERS})")
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "data" / "vehicles",
                    help="folder of real models with manifest.json (skipped when absent)")
    ap.add_argument("--no-real", action="store_true", help="generated vehicles only")
    ap.add_argument("--leave-out", default="", help="comma-separated real model files to leave out")
    ap.add_argument("--max-iter", type=int, default=None, help="boosting rounds (default: recipe)")
    ap.add_argument("--out", type=Path, default=ROOT / "ucad_cl" / "models" / "labeller.onnx")
    args = ap.parse_args(argv)
    if args.members < 1:
        ap.error("--members must be >= 1")
    try:
        from ucad_cl.labeller_train import train
    except ImportError as exc:                      # pragma: no cover - missing extra
        print(f"error: {exc}; install the training extra: pip install -e '.[train]'",
              file=sys.stderr)
        return 2
    real = None
    if not args.no_real:
        if (args.real / "manifest.json").exists():
            real = args.real
        else:
            print(f"note: no real models at {args.real}; training on generated vehicles only")
    train(args.out, vehicles=args.vehicles, seed=args.seed, real=real,
          leave_out=tuple(x for x in args.leave_out.split(",") if x),
          test_vehicles=args.test_vehicles, max_iter=args.max_iter, members=args.members)
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
