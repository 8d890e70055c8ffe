"""drcpo inside MMDetection3D 1.x's real KITTI train pipeline, on the CPU.

mmdet3d's ``KittiDataset`` on the KITTI sample (infos written in mmdet3d's own format from drcpo's
KITTI reader) with its KITTI train pipeline, ``DRCPOAugment`` in place of ``ObjectSample``. Needs
``pip install -e ".[test,mmdet3d]"`` and ``pip install --no-deps mmdet3d==1.4.0`` (see .ci/run)
and the KITTI sample in ``../shared``; mmdet3d_support.py stands in for ``mmcv._ext``.
"""
# ruff: noqa: NPY002

from __future__ import annotations

import importlib.util
import json
import multiprocessing
import os
import pickle
import subprocess
import sys
import types
from pathlib import Path

import mmdet3d_support as support
import numpy as np
import openpcdet_support as pcdet_support
import pytest
from kernel_support import loaded_kernels

# CI's MMDetection3D step sets DRCPO_REQUIRE_MMDET3D=1: there a missing piece fails instead.
_REQUIRED = os.environ.get("DRCPO_REQUIRE_MMDET3D") == "1"


def _skip(reason: str) -> None:
    if _REQUIRED:
        pytest.fail(f"DRCPO_REQUIRE_MMDET3D=1 but {reason}", pytrace=False)
    pytest.skip(reason, allow_module_level=True)


if not support.KITTI_SAMPLE.is_dir():
    _skip(f"KITTI sample not found under {support.SHARED} (only CI and developers have it)")
for _name in ("torch", "mmengine", "mmcv", "mmdet", "mmdet3d"):
    if importlib.util.find_spec(_name) is None:
        _skip(f"{_name} is not installed; see .ci/run's MMDetection3D step for the installs")
support.install()
import torch  # noqa: E402
from mmdet3d.registry import HOOKS, TRANSFORMS  # noqa: E402
from mmdet3d.structures import LiDARInstance3DBoxes, LiDARPoints  # noqa: E402
from mmengine.dataset import RepeatDataset  # noqa: E402
from mmengine.registry import DefaultScope  # noqa: E402

from drcpo.errors import ConfigError, DataError  # noqa: E402
from drcpo.geometry import box_corners  # noqa: E402
from drcpo.integrations.mmdet3d import (  # noqa: E402
    DRCPOAugment,
    DRCPOFadeHook,
    from_drcpo_boxes,
    to_drcpo_boxes,
)

SEED = 20230
# As mmdet3d's configs say (default_scope = 'mmdet3d'): type names resolve in mmdet3d's registries.
DefaultScope.get_instance("drcpo-mmdet3d-tests", scope_name="mmdet3d")


@pytest.fixture(scope="module")
def drcpo_db(tmp_path_factory):
    """drcpo's database of the sample, from its OpenPCDet dbinfos, indexed with a small K."""
    return pcdet_support.sample_database(tmp_path_factory.mktemp("mm") / "drcpo_db")


@pytest.fixture(scope="module")
def infos(tmp_path_factory):
    return support.write_mmdet3d_infos(
        support.KITTI_SAMPLE, tmp_path_factory.mktemp("infos") / "kitti_infos_train.pkl"
    )


def _drcpo(db, **kwargs):
    return dict(type="DRCPOAugment", db_path=str(db), classes=support.CLASS_NAMES, **kwargs)


def _samples(dataset, seed=SEED):
    # As mmengine's set_random_seed: numpy (flip, rotation, drcpo) and torch (PointShuffle).
    np.random.seed(seed)
    torch.manual_seed(seed)
    return [dataset[i] for i in range(len(dataset))]


def _arrays(sample):
    gt = sample["data_samples"].gt_instances_3d
    return sample["inputs"]["points"].numpy(), gt.bboxes_3d.tensor.numpy(), gt.labels_3d.numpy()


def _match_corners(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    """Whether the (8, 3) corner sets ``a`` and ``b`` are the same points in some order."""
    close = np.linalg.norm(a[:, None] - b[None], axis=-1) < atol
    return bool((close.sum(0) == 1).all() and (close.sum(1) == 1).all())


# Box conversion ---------------------------------------------------------------------------
def test_converted_boxes_have_drcpos_corners():
    rng = np.random.default_rng(7)
    n = 200
    boxes = np.column_stack(
        [
            rng.uniform(-30, 30, (n, 2)),
            rng.uniform(-3, 1, n),
            rng.uniform(0.3, 6, (n, 3)),
            rng.uniform(-2 * np.pi, 2 * np.pi, n),
        ]
    )
    mm = LiDARInstance3DBoxes(torch.from_numpy(from_drcpo_boxes(boxes)))
    ours = box_corners(boxes)
    theirs = mm.corners.numpy().astype(np.float64)
    assert all(_match_corners(theirs[i], ours[i], atol=1e-4) for i in range(n))
    # The other way round: mmdet3d's bottom-centre z is dz / 2 below drcpo's centre.
    np.testing.assert_allclose(to_drcpo_boxes(mm.tensor.numpy()), boxes, rtol=0, atol=1e-5)
    np.testing.assert_allclose(mm.gravity_center.numpy(), boxes[:, :3], rtol=0, atol=1e-5)


def test_box_conversion_round_trips_float32_exactly():
    rng = np.random.default_rng(8)
    values = rng.uniform(0.1, 40, (500, 7)).astype(np.float32)
    back = from_drcpo_boxes(to_drcpo_boxes(values)).astype(np.float32)
    np.testing.assert_array_equal(back, values)


# The transform on its own -----------------------------------------------------------------
def _results(infos, index=1):
    """mmdet3d's results dict after LoadPointsFromFile and LoadAnnotations3D."""
    dataset = support.dataset(infos, support.pipeline(dict(type="PointShuffle"))[:2], packed=False)
    return dataset.pipeline(dataset.get_data_info(index))


def test_transform_is_registered_and_keeps_mmdet3d_types(drcpo_db, infos):
    transform = TRANSFORMS.build(_drcpo(drcpo_db, stages=["gt_sampling"], seed=1))
    assert isinstance(transform, DRCPOAugment)
    results = _results(infos)
    before_boxes = results["gt_bboxes_3d"].tensor.clone()
    before_labels = results["gt_labels_3d"].copy()
    attribute_dims = results["points"].attribute_dims
    out = transform(results)
    points, boxes, labels = out["points"], out["gt_bboxes_3d"], out["gt_labels_3d"]
    assert isinstance(points, LiDARPoints) and points.tensor.dtype == torch.float32
    assert points.points_dim == 4 and points.attribute_dims == attribute_dims
    assert isinstance(boxes, LiDARInstance3DBoxes) and boxes.tensor.dtype == torch.float32
    assert labels.dtype == np.int64 and len(labels) == len(boxes) > len(before_labels)
    # The frame's own boxes come back bit for bit; the sampled ones have their class's sizes.
    m = len(before_labels)
    assert torch.equal(boxes.tensor[:m], before_boxes)
    np.testing.assert_array_equal(labels[:m], before_labels)
    database = transform.augmentor.pipeline.transforms[0].database
    for box, label in zip(boxes.tensor[m:].numpy(), labels[m:], strict=True):
        same = database.names == support.CLASS_NAMES[label]
        assert np.isclose(database.boxes[same, 3:6], box[3:6], atol=1e-5).all(1).any()


def test_ignored_labels_stay_minus_one(drcpo_db, infos):
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, stages=["gt_sampling"], seed=2)
    results = _results(infos)
    results["gt_labels_3d"] = np.full_like(results["gt_labels_3d"], -1)
    m = len(results["gt_labels_3d"])
    out = transform(results)
    assert (out["gt_labels_3d"][:m] == -1).all() and (out["gt_labels_3d"][m:] >= 0).all()


def test_per_sample_generators_ignore_call_order(drcpo_db, infos):
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, seed=3)
    forward = [transform(_results(infos, i))["gt_bboxes_3d"].tensor for i in (0, 1, 2)]
    backward = [transform(_results(infos, i))["gt_bboxes_3d"].tensor for i in (2, 1, 0)][::-1]
    assert all(torch.equal(a, b) for a, b in zip(forward, backward, strict=True))
    transform.epoch = 1  # another epoch, other draws
    assert not torch.equal(transform(_results(infos, 1))["gt_bboxes_3d"].tensor, forward[1])


def test_building_the_transform_warms_its_kernels_up(drcpo_db, monkeypatch):
    import importlib

    module = importlib.import_module("drcpo.warmup")  # drcpo.warmup is also the function
    warmed = []
    monkeypatch.setattr(module, "warmup", lambda transform: warmed.append(transform))
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES)
    assert warmed == [transform.augmentor.pipeline]
    DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, warmup=False)
    assert len(warmed) == 1


def _kernels_loaded_by_first_call(dataset, queue):
    torch.set_num_threads(1)  # as in a DataLoader worker
    (augment,) = [t for t in dataset.pipeline.transforms if isinstance(t, DRCPOAugment)]
    layouts = []

    def recording(results, transform=augment.transform):
        layouts.append(results["points"].tensor.numpy().flags.f_contiguous)
        return transform(results)

    augment.transform = recording
    before = loaded_kernels()
    np.random.seed(0)
    dataset[0]
    queue.put((loaded_kernels() - before, layouts[0]))


def kernels_loaded_in_worker(db: str, infos: str, warmup: bool) -> tuple[int, bool]:
    """In a fresh process: the kernels a worker forked once the dataset is built loads in its
    first sample, and whether the points DRCPOAugment got from LoadPointsFromFile were
    Fortran-ordered."""
    dataset = support.dataset(Path(infos), support.pipeline(_drcpo(db, warmup=warmup)))
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    worker = context.Process(target=_kernels_loaded_by_first_call, args=(dataset, queue))
    worker.start()
    loaded = queue.get(timeout=300)
    worker.join(timeout=60)
    return loaded


def _in_fresh_process(db, infos, warmup: bool) -> tuple[int, bool]:
    code = (
        "import json, sys; sys.path.insert(0, sys.argv[1]);"
        "import test_integrations_mmdet3d as t;"
        "print(json.dumps(t.kernels_loaded_in_worker(*sys.argv[2:4], sys.argv[4] == '1')))"
    )
    here = str(Path(__file__).parent)
    args = [sys.executable, "-c", code, here, str(db), str(infos), str(int(warmup))]
    done = subprocess.run(args, capture_output=True, text=True, timeout=600, check=True)
    return tuple(json.loads(done.stdout.strip().splitlines()[-1]))


def test_forked_worker_after_warmup_loads_no_kernels(drcpo_db, infos):
    """A freshly forked worker's first sample through mmdet3d's real pipeline loads no kernel
    after the warm-up done when the transform is built, although LoadPointsFromFile hands over
    Fortran-ordered points (the warm-up's are C-ordered: drcpo's frames make them C-contiguous,
    else each worker loaded another specialisation of a kernel). Without the warm-up the same
    sample loads several, so the count is live. (In a fresh process each, so that no earlier
    test has loaded the kernels.)"""
    assert _in_fresh_process(drcpo_db, infos, warmup=True) == (0, True)
    loaded, _ = _in_fresh_process(drcpo_db, infos, warmup=False)
    assert loaded > 0


def test_transform_pickles_for_spawned_workers(drcpo_db, infos):
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, seed=4)
    copy = pickle.loads(pickle.dumps(transform))
    a = transform(_results(infos))["points"].tensor
    assert torch.equal(copy(_results(infos))["points"].tensor, a)


def test_bad_arguments_name_the_culprit(drcpo_db, infos):
    with pytest.raises(ConfigError, match="DRCPOAugment: classes must list"):
        DRCPOAugment(str(drcpo_db))
    with pytest.raises(ConfigError, match=r"DRCPOAugment: stages \['nope'\] must list"):
        DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, stages=["nope"])
    with pytest.raises(ConfigError, match="DRCPOAugment: db_path"):
        DRCPOAugment(None, support.CLASS_NAMES)
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, warmup=False)
    results = _results(infos)
    results["gt_labels_3d"] = results["gt_labels_3d"] + 7
    with pytest.raises(DataError, match="gt_labels_3d .* must be -1 or indices into classes"):
        transform(results)
    results = _results(infos)
    boxes = results["gt_bboxes_3d"]
    results["gt_bboxes_3d"] = LiDARInstance3DBoxes(torch.zeros(len(boxes), 8), box_dim=8)
    with pytest.raises(DataError, match="box_dim 8"):
        transform(results)


def test_nine_value_boxes_keep_their_velocities(drcpo_db, infos):
    """box_dim 9 (vx, vy last): the frame's own boxes keep their velocities bit for bit, the
    inserted ones get the database's turned to their heading (none here: 0)."""
    transform = DRCPOAugment(str(drcpo_db), support.CLASS_NAMES, warmup=False, seed=1)
    results = _results(infos)
    seven = results["gt_bboxes_3d"].tensor
    velocity = torch.arange(2 * len(seven), dtype=torch.float32).reshape(-1, 2) + 1.0
    plain = transform(_results(infos))["gt_bboxes_3d"].tensor
    results["gt_bboxes_3d"] = LiDARInstance3DBoxes(torch.cat([seven, velocity], 1), box_dim=9)
    out = transform(results)["gt_bboxes_3d"]
    assert isinstance(out, LiDARInstance3DBoxes) and out.tensor.shape == (len(plain), 9)
    assert torch.equal(out.tensor[:, :7], plain) and len(plain) > len(seven)
    for box in out.tensor:
        own = torch.nonzero((seven == box[:7]).all(dim=1)).flatten()
        expected = velocity[own[0]] if len(own) else torch.zeros(2)
        assert torch.equal(box[7:], expected)


# mmdet3d's KITTI train pipeline -----------------------------------------------------------
@pytest.fixture(scope="module")
def drcpo_samples(drcpo_db, infos):
    return _samples(support.dataset(infos, support.pipeline(_drcpo(drcpo_db))))


def test_packed_output_matches_object_samples(drcpo_samples, infos, tmp_path):
    default = _samples(support.dataset(infos, support.pipeline(support.object_sample(tmp_path))))
    assert len(drcpo_samples) == len(default) == 6
    for ours, theirs in zip(drcpo_samples, default, strict=True):
        assert ours.keys() == theirs.keys() == {"inputs", "data_samples"}
        assert ours["inputs"].keys() == theirs["inputs"].keys() == {"points"}
        for a, b in zip(_arrays(ours), _arrays(theirs), strict=True):
            assert a.dtype == b.dtype and a.shape[1:] == b.shape[1:]
        gt_ours = ours["data_samples"].gt_instances_3d
        gt_theirs = theirs["data_samples"].gt_instances_3d
        assert type(gt_ours.bboxes_3d) is type(gt_theirs.bboxes_3d) is LiDARInstance3DBoxes
        assert set(ours["data_samples"].metainfo) == set(theirs["data_samples"].metainfo)


def test_packed_boxes_lie_in_range_with_known_labels(drcpo_samples):
    low, high = np.array(support.POINT_RANGE[:2]), np.array(support.POINT_RANGE[3:5])
    inserted = 0
    for sample in drcpo_samples:
        points, boxes, labels = _arrays(sample)
        assert points.dtype == np.float32 and points.shape[1] == 4
        assert ((points[:, :2] >= low) & (points[:, :2] <= high)).all()
        assert ((boxes[:, :2] >= low) & (boxes[:, :2] <= high)).all()
        assert labels.dtype == np.int64 and ((labels >= 0) & (labels < 3)).all()
        assert len(labels) == len(boxes)
        inserted += len(labels)
    assert inserted > 6 * 3  # objects were added


def test_same_seed_same_samples(drcpo_db, infos, drcpo_samples):
    again = _samples(support.dataset(infos, support.pipeline(_drcpo(drcpo_db))))
    for a, b in zip(drcpo_samples, again, strict=True):
        for x, y in zip(_arrays(a), _arrays(b), strict=True):
            np.testing.assert_array_equal(x, y)
    other = _samples(support.dataset(infos, support.pipeline(_drcpo(drcpo_db))), seed=SEED + 1)
    assert any(
        _arrays(a)[1].shape != _arrays(b)[1].shape
        or not np.array_equal(_arrays(a)[1], _arrays(b)[1])
        for a, b in zip(drcpo_samples, other, strict=True)
    )


def _loader_samples(dataset, seed):
    """All samples through a DataLoader with 2 forked workers seeded by mmengine's
    worker_init_fn, as mmengine's runner builds it (``randomness=dict(seed=seed)``)."""
    from functools import partial

    from mmengine.dataset import pseudo_collate, worker_init_fn

    init = partial(worker_init_fn, num_workers=2, rank=0, seed=seed)
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=2,
        num_workers=2,
        worker_init_fn=init,
        collate_fn=pseudo_collate,
        multiprocessing_context="fork",
    )
    return [_arrays({"inputs": i, "data_samples": d}) for b in loader for i, d in _unbatch(b)]


def _unbatch(batch):
    pairs = zip(batch["inputs"]["points"], batch["data_samples"], strict=True)
    return [({"points": p}, d) for p, d in pairs]


def test_loader_workers_seeded_by_mmengine_give_the_same_samples(drcpo_db, infos):
    dataset = support.dataset(infos, support.pipeline(_drcpo(drcpo_db)))
    first, again = _loader_samples(dataset, SEED), _loader_samples(dataset, SEED)
    assert len(first) == 6
    for a, b in zip(first, again, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    other = _loader_samples(dataset, SEED + 1)
    pairs = zip(first, other, strict=True)
    assert any(a[1].shape != b[1].shape or (a[1] != b[1]).any() for a, b in pairs)


# The fade hook ----------------------------------------------------------------------------
class _Loader:
    """What the hook reads of mmengine's train loader."""

    def __init__(self, dataset, persistent_workers=False):
        self.dataset = dataset
        self.persistent_workers = persistent_workers
        self._iterator = object()


def _runner(loader, epoch, max_epochs):
    messages = []
    logger = types.SimpleNamespace(info=messages.append)
    return types.SimpleNamespace(
        train_dataloader=loader, epoch=epoch, max_epochs=max_epochs, logger=logger
    )


def test_fade_hook_turns_drcpo_off_for_the_last_epochs(drcpo_db, infos):
    dataset = support.dataset(infos, support.pipeline(_drcpo(drcpo_db, seed=5))[:3], packed=False)
    plain = support.dataset(infos, support.pipeline(_drcpo(drcpo_db))[:2], packed=False)
    hook = HOOKS.build(dict(type="DRCPOFadeHook", num_last_epochs=2))
    assert isinstance(hook, DRCPOFadeHook)
    loader = _Loader(RepeatDataset(dataset, times=2))  # found through the wrapper
    counts = []
    for epoch in range(4):
        hook.before_train_epoch(_runner(loader, epoch, max_epochs=4))
        counts.append(len(dataset[1]["gt_labels_3d"]))
    original = len(plain[1]["gt_labels_3d"])
    assert counts[0] > original and counts[1] > original
    assert counts[2:] == [original, original]
    transform = dataset.pipeline.transforms[2]
    assert transform.disabled and transform.epoch == 3


def test_fade_hook_restarts_persistent_workers_only_on_a_change(drcpo_db, infos):
    dataset = support.dataset(
        infos, support.pipeline(_drcpo(drcpo_db, warmup=False))[:3], packed=False
    )
    hook = DRCPOFadeHook(num_last_epochs=1)
    loader = _Loader(dataset, persistent_workers=True)
    hook.before_train_epoch(_runner(loader, 0, max_epochs=3))
    # test seam: mmengine's loader (torch's DataLoader) holds persistent workers in _iterator
    assert loader._iterator is not None  # unseeded and still on: the workers are up to date
    hook.before_train_epoch(_runner(loader, 2, max_epochs=3))
    assert loader._iterator is None


def test_fade_hook_needs_a_drcpo_transform(infos):
    hook = DRCPOFadeHook(num_last_epochs=1)
    with pytest.raises(ConfigError, match="no DRCPOAugment"):
        hook.before_train_epoch(_runner(_Loader(support.dataset(infos, [], packed=False)), 0, 2))
    with pytest.raises(ConfigError, match="num_last_epochs must be >= 0"):
        DRCPOFadeHook(num_last_epochs=-1)


def test_importing_registers_without_loading_mmdet3ds_datasets():
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import drcpo.integrations.mmdet3d\n"
        "from mmdet3d.registry import HOOKS, TRANSFORMS\n"
        "print('DRCPOAugment' in TRANSFORMS.module_dict, 'DRCPOFadeHook' in HOOKS.module_dict,\n"
        "      any(m in sys.modules for m in ('mmdet3d.datasets', 'mmdet3d.structures')))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["True", "True", "False"], run.stderr


def test_fade_hook_in_mmengines_training_loop(drcpo_db, infos, tmp_path):
    """A real mmengine Runner (3 epochs, 2 persistent workers) with the hook from the config:
    drcpo adds objects in epochs 0 and 1, none in the last."""
    from mmengine.model import BaseModel
    from mmengine.runner import Runner

    class Count(BaseModel):
        """Records how many boxes each batch holds; its loss is a zero that can step."""

        def __init__(self):
            super().__init__()
            self.weight = torch.nn.Parameter(torch.zeros(1))
            self.boxes: list[int] = []

        def forward(self, inputs, data_samples=None, mode="loss"):
            self.boxes.append(sum(len(d.gt_instances_3d.labels_3d) for d in data_samples))
            return {"loss": self.weight.sum() * 0.0}

    model = Count()
    runner = Runner(
        model=model,
        work_dir=str(tmp_path),
        train_dataloader=dict(
            dataset=support.dataset(infos, support.pipeline(_drcpo(drcpo_db))),
            sampler=dict(type="DefaultSampler", shuffle=False),
            batch_size=6,
            num_workers=2,
            persistent_workers=True,
            collate_fn=dict(type="pseudo_collate"),
        ),
        train_cfg=dict(by_epoch=True, max_epochs=3),
        optim_wrapper=dict(optimizer=dict(type="SGD", lr=0.0)),
        custom_hooks=[dict(type="DRCPOFadeHook", num_last_epochs=1)],
        default_hooks=dict(checkpoint=None, logger=None),
        randomness=dict(seed=SEED),
        default_scope="mmdet3d",
    )
    runner.train()
    plain = support.dataset(infos, support.pipeline(dict(type="PointShuffle")))
    original = sum(len(_arrays(plain[i])[2]) for i in range(len(plain)))
    first, second, last = model.boxes
    assert first > original and second > original and last == original
