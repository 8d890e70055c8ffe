"""A small CenterPoint-style BEV detector trained on CPU, for the detection benchmark.

Not part of drcpo (it needs torch, an optional extra: ``pip install -e ".[detection]"``).
Modules: :mod:`.bev` (point cloud to BEV features), :mod:`.heads` (heatmap and box targets,
decoding, KITTI result lines; numpy only), :mod:`.model` (the CNN and its loss),
:mod:`.train` (the training loop and inference), :mod:`.scoring` (AP through
:mod:`drcpo.evaluation`, heading error).
"""
