"""Run OpenPCDet's unmodified ``kitti_object_eval_python`` on label folders; print JSON APs.

Usage: ``NUMBA_ENABLE_CUDASIM=1 python kitti_reference_eval.py OPENPCDET_EVAL_DIR GT_DIR DT_DIR``

Run in its own process: numba reads ``NUMBA_ENABLE_CUDASIM`` when it is first imported, and the
reference's ``rotate_iou.py`` compiles CUDA kernels at import (the simulator runs them on the
CPU). Its modules are loaded from their files as one package, so OpenPCDet's ``pcdet``
package (which imports torch) is never imported. ``kitti_common`` imports ``skimage.io`` for
images only; a stand-in module satisfies that import (no image is read).

Printed: ``{"bbox"|"bev"|"3d"|"aos": {"R11"|"R40": [[[AP per overlap set] per difficulty]
per class]}}`` for Car, Pedestrian, Cyclist, from the reference's precision arrays.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
from pathlib import Path


def load_reference(directory: Path) -> types.ModuleType:
    sys.modules.setdefault("skimage", types.ModuleType("skimage"))
    sys.modules["skimage"].io = types.ModuleType("skimage.io")
    spec = importlib.util.spec_from_file_location(
        "kitti_eval_reference",
        directory / "__init__.py",
        submodule_search_locations=[str(directory)],
    )
    package = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = package
    spec.loader.exec_module(package)
    for name in ("rotate_iou", "eval", "kitti_common"):
        __import__(f"{spec.name}.{name}")
    return package


def main() -> None:
    directory, gt_dir, dt_dir = (Path(arg) for arg in sys.argv[1:4])
    package = load_reference(directory)
    common, evaluation = package.kitti_common, package.eval
    ids = sorted(int(path.stem) for path in Path(gt_dir).glob("*.txt"))
    gt_annos = common.get_label_annos(str(gt_dir), ids)
    dt_annos = common.get_label_annos(str(dt_dir), ids)
    details: dict = {}
    evaluation.get_official_eval_result(gt_annos, dt_annos, [0, 1, 2], PR_detail_dict=details)
    out = {
        metric: {
            "R11": evaluation.get_mAP(precision).tolist(),
            "R40": evaluation.get_mAP_R40(precision).tolist(),
        }
        for metric, precision in details.items()
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
