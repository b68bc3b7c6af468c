"""What each of issue 19's changes does on the real development sequences (SemanticKITTI 04 / 05 /
08, 10 frames each, the ESPNetv2 segmentation as in bench/clutter.py).

`ClutterConfig`'s defaults in both modes, then the defaults with one change switched off, in the
same run: the difference is that change's effect on streets the rules were developed on. This
is not the leave-one-sequence-out evaluation (bench/clutter.py chooses the grid's thresholds on
the other sequences); it runs the shipped defaults as they are.

`--shape-models a.pt,b.pt` adds clutter-mode rows of the defaults with another vehicle shape
classifier than the shipped one (a candidate, `mmsclean train clutter-shapes --out`).

Usage: python -m bench.clutter_ablation [--sequences 04,05,08] [--shape-models a.pt,b.pt]
[--no-record]
Needs MMSCLEAN_REAL_DATA and MMSCLEAN_WEIGHTS_DIR.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.shapes import load_vehicle_shapes
from bench.clutter import load, run, score
from bench.clutter_shapes import trained_on
from bench.clutter_situations import BEFORE, CHANGES
from bench.common import append_results, markdown_table

COMMAND = (
    "MMSCLEAN_REAL_DATA=../shared/data MMSCLEAN_WEIGHTS_DIR=../shared/models "
    "MMSCLEAN_DATA_DIR=/tmp/mmsvar .venv/bin/python -m bench.clutter_ablation"
)
# the defaults, each change off alone, and every change off (issue 5's fusion)
VARIANTS = {
    "defaults": {},
    **{f"- {name}": {key: BEFORE[key]} for name, key in CHANGES.items()},
    "before (all off)": BEFORE,
}
HEADER = ["mode", "pipeline", "sequence", "SA 360", "DA 360", "AA 360", "OA view",
          "clutter om. view", "map om. view", "map com. view", "clutter om. 360",
          "map om. 360"]  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", default="04,05,08")
    parser.add_argument("--shape-models", default="", help="candidate shape checkpoints")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    real = os.environ.get("MMSCLEAN_REAL_DATA")
    if not real:
        print("MMSCLEAN_REAL_DATA is not set", file=sys.stderr)
        return 2
    seqs = [load(Path(real), n.strip()) for n in args.sequences.split(",") if n.strip()]
    candidates = {Path(p).name: Path(p) for p in args.shape_models.split(",") if p.strip()}
    runs = [(mode, variant, changes, None) for mode in ("dynamic", "clutter")
            for variant, changes in VARIANTS.items()]  # fmt: skip
    runs += [("clutter", f"defaults, shapes {name}", {}, load_vehicle_shapes(path))
             for name, path in candidates.items()]  # fmt: skip
    rows = []
    for mode, variant, changes, shape_model in runs:
        for seq in seqs:
            result = run(seq, ClutterConfig(mode=mode, **changes), shape_model)
            m = score(seq, result.removed, result.in_view)
            d = m["full"]["dynamic"]["scores"]
            e = m["in_view"]["clutter"]["error_matrix"]
            f = m["full"]["clutter"]["error_matrix"]
            rows.append([mode, variant, seq.name, f"{d['SA']:.2f}", f"{d['DA']:.2f}",
                         f"{d['AA']:.2f}", f"{e['overall_accuracy']:.2f}",
                         f"{e['clutter_omission']:.2f}", f"{e['map_omission']:.2f}",
                         f"{e['map_commission']:.3f}", f"{f['clutter_omission']:.2f}",
                         f"{f['map_omission']:.2f}"])  # fmt: skip
            print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(HEADER, rows)
    notes = (
        "Real data, SemanticKITTI 04 / 05 / 08 (10 frames each), ESPNetv2 Cityscapes masks. "
        "'defaults' is ClutterConfig as shipped; '- X' the defaults with issue 19's change X "
        "off; 'before' all of them off (issue 5's fusion with today's thresholds). Dynamic mode "
        "is scored on the full 360 degree map (SA / DA / AA), clutter mode inside the camera "
        "view as the paper scores it (overall accuracy, clutter omission, map omission, map "
        "commission, per cent) and, as the exported map holds it, on the full 360 degree map "
        "(clutter and map omission). "
        "The shipped defaults, not leave-one-sequence-out: the thresholds were developed on "
        "these sequences."
        + "".join(f" 'shapes {name}': the defaults with the vehicle shape classifier {path} "
                  f"(its card: {trained_on(path)})." for name, path in candidates.items())
    )  # fmt: skip
    print(f"\n{table}\n{notes}")
    if not args.no_record:
        append_results(
            "Clutter: issue 19's changes one by one on SemanticKITTI",
            COMMAND + (f" --shape-models {args.shape_models}" if candidates else ""),
            table,
            notes,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
