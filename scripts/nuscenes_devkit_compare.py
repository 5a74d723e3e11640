"""Compare ``envs.data.NuScenesTracking`` with a devkit dump (``nuscenes_devkit_dump.py``).

    PYTHONPATH=. python scripts/nuscenes_devkit_compare.py DATAROOT VERSION DUMP.json [--tol 1e-4]

Checks, over split ``all``: the instances loaded are exactly the devkit's instances of mapped
categories; each has the devkit's annotation count; every annotation's LIDAR_TOP box matches the
devkit's to ``tol`` (metres for centre and size, radians for the wrapped yaw difference). Exit
status 1 on any mismatch.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def compare(root: str, version: str, dump: dict, tol: float = 1e-4) -> dict:
    """``{"instances", "annotations", "max_centre_size_err", "max_yaw_err", "errors"}``."""
    from envs.data.nuscenes import CATEGORY_MAP, NuScenesTracking

    data = NuScenesTracking(root, version, "all")
    errors: list[str] = []
    expected = {t for t, c in dump["categories"].items() if c in CATEGORY_MAP}
    loaded = set(data.instance_tokens)
    if loaded != expected:
        errors.append(
            f"instances: {len(loaded - expected)} extra, {len(expected - loaded)} "
            f"missing of {len(expected)}"
        )
    max_pos = max_yaw = 0.0
    n = 0
    for tr, inst, anns in zip(
        data.tracklets, data.instance_tokens, data.annotation_tokens, strict=True
    ):
        if dump["counts"].get(inst) != len(tr):
            errors.append(
                f"instance {inst}: {len(tr)} annotations, devkit {dump['counts'].get(inst)}"
            )
        for box, token in zip(tr.boxes, anns, strict=True):
            ref = dump["boxes"].get(token)
            if ref is None:
                errors.append(f"annotation {token}: not returned by the devkit")
                continue
            ref = np.asarray(ref)
            pos = float(np.abs(box[:6] - ref[:6]).max())
            yaw = float(abs((box[6] - ref[6] + np.pi) % (2 * np.pi) - np.pi))
            max_pos, max_yaw, n = max(max_pos, pos), max(max_yaw, yaw), n + 1
            if pos > tol or yaw > tol:
                errors.append(f"annotation {token}: box {box.tolist()} vs devkit {ref.tolist()}")
    return {
        "instances": len(loaded),
        "annotations": n,
        "max_centre_size_err": max_pos,
        "max_yaw_err": max_yaw,
        "errors": errors,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root")
    parser.add_argument("version")
    parser.add_argument("dump")
    parser.add_argument("--tol", type=float, default=1e-4)
    args = parser.parse_args()
    with open(args.dump) as f:
        dump = json.load(f)
    report = compare(args.root, args.version, dump, args.tol)
    for line in report["errors"][:20]:
        print("MISMATCH", line)
    print(
        f"{report['instances']} instances, {report['annotations']} annotations; max |centre/size"
        f" diff| {report['max_centre_size_err']:.2e} m, max |yaw diff| "
        f"{report['max_yaw_err']:.2e} rad; {len(report['errors'])} mismatches (tol {args.tol})"
    )
    return 1 if report["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
