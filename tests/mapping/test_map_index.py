"""The map index relocalization looks things up in (#20 item 2): the same answers as
comparing with every object of the map, and a map of several rooms relocalizes a room's
queries as well as the room's own map."""
from dataclasses import replace

import numpy as np
import pytest

from rfm_core.evaluation.pipeline import relocalize_capture, run_capture
from rfm_core.evaluation.trajectory import map_to_truth
from rfm_core.geometry import Pose4, iou_3d_paired
from rfm_core.mapping.map_index import track_boxes
from rfm_core.mapping.mapper import Mapper, MapperConfig
from rfm_core.sim.capture import Capture, CaptureConfig


@pytest.fixture(scope='module')
def room():
    return run_capture(CaptureConfig(seed=41, frames=50, fps=5), 'ground_truth:rgbd', noise_seed=3)


def test_the_index_finds_every_overlap_and_the_most_similar_keyframes(room):
    """Boxes scattered over the room (some copies of mapped ones, shifted a little): the
    index's overlaps equal a comparison with every box of the map; retrieval equals ranking
    every keyframe's descriptor."""
    mapper = room.mapper
    index = mapper.map_index()
    targets = track_boxes(mapper.tracks())
    rng = np.random.default_rng(0)
    boxes = targets[rng.choice(len(targets), 60)].copy()
    boxes[:, :3] += rng.normal(0, 0.15, (60, 3))
    boxes[:30, 3:6] *= rng.uniform(0.5, 1.5, (30, 3))
    boxes[40:, :3] = rng.uniform(targets[:, :3].min(0) - 1, targets[:, :3].max(0) + 1, (20, 3))
    iou = np.array([iou_3d_paired(np.repeat(b[None], len(targets), 0), targets).max() for b in boxes])
    found = index.overlapping(boxes, 0.25)
    np.testing.assert_array_equal(found, iou >= 0.25)
    assert 10 < found.sum() < 60
    for k in list(mapper.keyframes)[::3]:
        view = mapper.keyframes[k]
        ids = [i for i in mapper.poses if len(mapper.keyframes[i]) >= 2]
        sims = np.array([mapper._descriptors[i] @ _unit_mean(view.embeddings) for i in ids])
        assert index.candidates(view, 5) == [ids[i] for i in np.argsort(-sims, kind='stable')[:5]]


def _unit_mean(embeddings):
    v = embeddings.astype(np.float64).mean(0)
    return v / np.linalg.norm(v)


def test_a_map_of_several_rooms_relocalizes_a_room_as_its_own_map_does(room):
    """The room's map next to four other rooms' (15 m apart, one map): a second walk through
    the room relocalizes as often and as well as against the room's map alone, every pose in
    the right room."""
    building = Mapper(MapperConfig(posed=True))
    for r, mapped in enumerate([room] + [run_capture(CaptureConfig(seed=s, frames=40, fps=5), 'ground_truth:rgbd',
                                                     noise_seed=3) for s in (42, 43, 44, 45)]):
        shift = Pose4(0.0, (-15.0 * r, 0.0, 0.0))                                # T_room_building
        for k, obs in mapped.mapper.keyframes.items():
            building.add_keyframe(1000 * r + k, obs)
        for k, pose in mapped.mapper.poses.items():
            building.set_keyframe_pose(1000 * r + k, pose @ shift)
        for e in mapped.mapper.active_edges():
            building.add_edge(replace(e, source=1000 * r + e.source, target=1000 * r + e.target))
    building.update()
    building.mode = room.mapper.mode = 'localization'
    assert len(building.tracks()) > 2 * len(room.mapper.tracks())
    world = map_to_truth(room.mapper.camera_poses(), room.truth)
    second = CaptureConfig(seed=41, frames=20, fps=2, trajectory_seed=1)
    alone = relocalize_capture(room.mapper, world, Capture(second), 'ground_truth:rgbd', noise_seed=11)
    together = relocalize_capture(building, world, Capture(second), 'ground_truth:rgbd', noise_seed=11)
    assert alone['registered'] >= 0.85, alone
    assert together['registered'] >= alone['registered'] - 0.05 and together['wrong'] == 0.0, together
    assert together['ATE_median'] < 0.05 and together['ARE_median'] < 2.0, together


def test_the_maps_depth_points_whole_or_in_tiles(room, monkeypatch):
    """The registered keyframes' clouds lifted into the map and merged: a point a keyframe
    measured lies in the map's cloud where its pose puts it; a map too large for one cloud is
    merged per tile from the keyframes near it, and a camera elsewhere gets another tile."""
    from rfm_core.mapping import map_index  # noqa: PLC0415
    mapper = room.mapper
    rng = np.random.default_rng(3)
    keyframes = {}
    for k, obs in mapper.keyframes.items():          # each keyframe measured a patch of floor near its camera
        if k in mapper.poses:
            centre = mapper.poses[k].inverse().t
            patch = np.c_[centre[:2] + rng.uniform(-1.5, 1.5, (400, 2)), np.full(400, centre[2] - 1.3)]
            obs = replace(obs, cloud=mapper.poses[k].transform_points(patch).astype(np.float32))
        keyframes[k] = obs
    index = type(mapper.map_index())(keyframes, dict(mapper.poses), {}, [])
    whole = index.cloud_near(np.zeros(3))
    assert index.cloud_near(np.array([50.0, 0.0, 0.0])) is whole          # one cloud, wherever the camera
    k = next(iter(mapper.poses))
    lifted = mapper.poses[k].inverse().transform_points(np.asarray(keyframes[k].cloud, float))
    d, _ = whole.point_index().tree.query(lifted)
    assert np.median(d) < map_index.CLOUD_VOXEL_M
    assert len(whole.cloud) < sum(len(keyframes[i].cloud) for i in mapper.poses)    # merged
    monkeypatch.setattr(map_index, 'CLOUD_MAX_POINTS', 10)
    tiled = type(index)(keyframes, dict(mapper.poses), {}, [])
    at = np.r_[(np.floor(lifted.mean(0)[:2] / map_index.CLOUD_TILE_M) + 0.5) * map_index.CLOUD_TILE_M, 0.0]
    here = tiled.cloud_near(at)                                            # the middle of the tile
    assert 0 < len(here.cloud) <= len(whole.cloud)
    assert tiled.cloud_near(at + 1.0) is here                              # the same tile
    assert len(tiled.cloud_near(np.array([100.0, 100.0, 0.0])).cloud) == 0  # no keyframe near
