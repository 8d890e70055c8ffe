"""The ground-truth database (paper step 1): every labelled object's points in its canonical pose.

:mod:`~drcpo.database.store` reads and writes it (memory-mapped arrays, a manifest with
checksums); :mod:`~drcpo.database.build` cuts it out of KITTI frames or any data set of frames;
:mod:`~drcpo.database.dbinfos` imports OpenPCDet's and MMDetection3D's databases, whose pickled
infos :mod:`~drcpo.database.safe_pickle` reads without running any code (the globals such a
pickle may name: :mod:`~drcpo.database.pickle_globals`).
"""

from drcpo.database import safe_pickle
from drcpo.database.build import DEFAULT_CLASSES, build_database
from drcpo.database.dbinfos import import_mmdet3d, import_openpcdet, validate_dbinfos
from drcpo.database.store import (
    DATABASE_OUTPUT,
    GroundTruthDatabase,
    ObjectRecord,
    difficulty_name,
    read_manifest,
)

__all__ = [
    "DATABASE_OUTPUT",
    "DEFAULT_CLASSES",
    "GroundTruthDatabase",
    "ObjectRecord",
    "build_database",
    "difficulty_name",
    "import_mmdet3d",
    "import_openpcdet",
    "read_manifest",
    "safe_pickle",
    "validate_dbinfos",
]
