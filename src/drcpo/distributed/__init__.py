"""Data-set-wide work spread over worker processes, each giving the same bytes as one process:
offline generation on this machine without Ray (:func:`augment_kitti_processes`), or over a Ray
cluster (the optional extra ``drcpo[ray]``): offline generation (:func:`augment_kitti_cluster`),
the database (:func:`build_database_cluster`; any data set of frames:
:func:`build_dataset_cluster`) and the index (:func:`build_index_cluster`). A local cluster by
default, a cluster's address when given (:func:`connect`)."""

from __future__ import annotations

from drcpo.distributed.augment import augment_kitti_cluster
from drcpo.distributed.build import build_database_cluster, build_dataset_cluster
from drcpo.distributed.cluster import Cluster, WorkerLost, connect, require_ray
from drcpo.distributed.index import build_index_cluster
from drcpo.distributed.local import augment_kitti_processes

__all__ = [
    "Cluster",
    "WorkerLost",
    "augment_kitti_cluster",
    "augment_kitti_processes",
    "build_database_cluster",
    "build_dataset_cluster",
    "build_index_cluster",
    "connect",
    "require_ray",
]
