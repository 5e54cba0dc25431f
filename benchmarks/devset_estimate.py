"""Score estimation output (JSON Lines) against the ground truth in scene files.

    python -m benchmarks.devset_estimate --scenes ../shared/devset/direct --estimates lights.jsonl

Prints per scene: lights found / true, position error (of scene size), angular
error (degrees), seconds; then the median position error and the success rate.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from render import GBuffer
from selfsup.metrics import light_errors
from selfsup.scenes.io import read_scene


def score(scenes: str | Path, estimates: str | Path) -> list[dict]:
    by_id = {}
    for path in sorted(Path(scenes).glob("*.npz")):
        scene = read_scene(path)
        by_id[scene.id] = scene
    rows = []
    for line in Path(estimates).read_text().splitlines():
        record = json.loads(line)
        scene = by_id[record["id"]]
        g = GBuffer.from_depth(scene.depth[None], scene.K[None])
        centroid = g.points[0][g.mask[0]].mean(0)
        pos = torch.tensor([l["position"] for l in record["lights"]]).reshape(-1, 3)
        err = light_errors(pos, None, scene.light_pos, None, float(scene.scene_scale), centroid)
        rows.append({"id": record["id"], "found": len(record["lights"]), "true": scene.light_pos.shape[0],
                     "position": [round(e, 4) for e in err.position], "angular": [round(a, 1) for a in err.angular],
                     "success": err.success, "seconds": record["seconds"]})
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", required=True)
    parser.add_argument("--estimates", required=True)
    args = parser.parse_args()
    rows = score(args.scenes, args.estimates)
    for row in rows:
        print(row)
    worst = sorted(max(r["position"]) for r in rows)
    print(f"median position error {worst[len(worst) // 2]:.4f}; success {sum(r['success'] for r in rows)}/{len(rows)}; "
          f"right light count {sum(r['found'] == r['true'] for r in rows)}/{len(rows)}")
