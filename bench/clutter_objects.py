"""Clutter removal on one simulated situation street, object by object: for each movable object
the camera's view holds, how much of it the pipeline kept, which tracks hold it and what each
track's evidence says (frames, P(vehicle) by 3D shape, camera class and the share of the frames
that classed it). A diagnostic for development: it records nothing. Synthetic.

Run it on the development seeds (1, 2, 3); the held-out seeds are for `bench.clutter_situations`
only. The street and the modelled camera are `bench.clutter_situations`' (cached there).

Usage: python -m bench.clutter_objects SITUATION SEED [--top N]
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict

import numpy as np

from app.io import open_survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.pipeline import ClutterPipeline
from bench.clutter_situations import SITUATIONS, modelled_class_maps, simulated
from bench.common import markdown_table

MOVABLE = np.r_[10:33, 252:260]  # SemanticKITTI's vehicles, persons, riders, moving ones


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("situation", choices=[s.name for s in SITUATIONS])
    parser.add_argument("seed", type=int)
    parser.add_argument("--top", type=int, default=3, help="tracks shown per object")
    args = parser.parse_args()
    situation = next(s for s in SITUATIONS if s.name == args.situation)
    path = simulated(situation, args.seed)
    survey = open_survey(path, "sim")
    result = ClutterPipeline(ClutterConfig(mode=situation.mode), modelled_class_maps(path)).run(
        survey
    )
    scene = json.loads((path / "ground_truth" / "scene.json").read_text())["objects"]
    names = {o["instance"]: o["name"] for o in scene}
    tracks = result.tracks
    points, kept, frames = Counter(), Counter(), Counter()
    held: dict[int, Counter] = defaultdict(Counter)  # object -> track -> frames it held most
    for i, frame in enumerate(survey.frames):
        reference = frame.reference_labels()
        evidence = result.evidence[i]
        seen = result.in_view[i] & np.isin(reference["semantic"], MOVABLE)
        instance = reference["instance"]
        for k in np.unique(instance[seen]):
            on = seen & (instance == k)
            points[k] += int(on.sum())
            kept[k] += int((on & ~result.removed[i]).sum())
            frames[k] += 1
            clusters = evidence.cluster[on]
            clusters = clusters[clusters >= 0]
            if len(clusters) and tracks is not None:
                held[k][int(tracks.cluster_track[i][np.bincount(clusters).argmax()])] += 1
    rows = []
    for k in sorted(points, key=lambda k: -kept[k]):
        described = []
        for t, count in held[k].most_common(args.top):
            if t < 0:
                described.append(f"untracked in {count}")
                continue
            described.append(
                f"track {t} in {count} (frames {tracks.frame_counts[t]}, "
                f"P {tracks.vehicle_shape[t]:.2f}, camera {tracks.camera_class[t]}, "
                f"classed {tracks.class_share[t]:.2f})"
                if tracks.vehicle_shape is not None
                else f"track {t} in {count}"
            )
        rows.append([str(k), names.get(int(k), "?"), f"{points[k]:,}",
                     f"{100 * kept[k] / points[k]:.1f}", str(frames[k]),
                     "; ".join(described)])  # fmt: skip
    total, left = sum(points.values()), sum(kept.values())
    print(f"{situation.name}, seed {args.seed}: {left:,} of {total:,} movable points in the view "
          f"kept ({100 * left / max(total, 1):.1f} %)")  # fmt: skip
    header = ["object", "kind", "points in view", "kept %", "frames", "its tracks"]
    print(markdown_table(header, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
