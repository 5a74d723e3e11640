"""Dump what the official nuScenes devkit reads from a dataset: every annotation's box in its key
frame's LIDAR_TOP frame (``NuScenes.get_sample_data``) and every instance's annotation count
(walking its ``first_annotation_token`` / ``next`` chain).

Runs in the devkit's own virtual environment (no project imports; see
``scripts/check_nuscenes_devkit.sh``)::

    python scripts/nuscenes_devkit_dump.py DATAROOT VERSION OUT.json

OUT.json: ``{"boxes": {annotation_token: [x, y, z, l, w, h, yaw]}, "counts": {instance_token:
n}, "categories": {instance_token: name}}``, boxes with nuScenes ``wlh`` reordered to
``(l, w, h)`` and yaw = ``orientation.yaw_pitch_roll[0]``.
"""

from __future__ import annotations

import json
import sys


def dump(dataroot: str, version: str) -> dict:
    from nuscenes.nuscenes import NuScenes

    nusc = NuScenes(version=version, dataroot=dataroot, verbose=False)
    boxes = {}
    for sample in nusc.sample:
        _, found, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
        for box in found:
            w, l, h = (float(v) for v in box.wlh)
            x, y, z = (float(v) for v in box.center)
            boxes[box.token] = [x, y, z, l, w, h, float(box.orientation.yaw_pitch_roll[0])]
    counts, categories = {}, {}
    for inst in nusc.instance:
        categories[inst["token"]] = nusc.get("category", inst["category_token"])["name"]
        n, token = 0, inst["first_annotation_token"]
        while token:
            n += 1
            token = nusc.get("sample_annotation", token)["next"]
        counts[inst["token"]] = n
    return {"boxes": boxes, "counts": counts, "categories": categories}


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: nuscenes_devkit_dump.py DATAROOT VERSION OUT.json")
    result = dump(sys.argv[1], sys.argv[2])
    with open(sys.argv[3], "w") as f:
        json.dump(result, f)
    print(f"devkit: {len(result['boxes'])} boxes, {len(result['counts'])} instances")
