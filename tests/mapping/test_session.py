"""MapSession: keyframe ids from a view graph that restarts, or that meets a loaded map (#19)."""
import numpy as np
import pytest
from sim_frames import detected_frames

from rfm_core.mapping.map_io import load_map, save_map
from rfm_core.mapping.mapper import EdgeRecord, Mapper
from rfm_core.matching.view_graph import ViewGraphBuilder
from rfm_core.session import MAX_KEYFRAME_ID, MapSession, SequenceCheck


@pytest.fixture(scope='module')
def observations():
    return detected_frames(frames=50)


def _feed(session: MapSession, frames, expected: set) -> int:
    """The frames through a new view graph (a matcher started afresh) into ``session``;
    ``expected`` collects its edges as pairs of keyframe stamps. Returns its keyframe count."""
    graph = ViewGraphBuilder(session.mapper.config.matching)
    stamps = {}
    for obs in frames:
        keyframe, edges, track = graph.add(obs)
        if keyframe is not None:
            stamps[keyframe.keyframe_id] = keyframe.observations.stamp_ns
            session.add_keyframe(keyframe.keyframe_id, keyframe.observations)
            for e in edges:
                expected.add(frozenset((stamps[e.source_id], stamps[e.target_id])))
                session.add_edge(EdgeRecord.from_edge(e))
        if track is not None:
            session.add_frame(track)
    session.update(force_full=True)
    return len(stamps)


def _edges_by_stamp(mapper: Mapper) -> set:
    kf = mapper.keyframes
    return {frozenset((kf[e.source].stamp_ns, kf[e.target].stamp_ns)) for e in mapper.edges.values()}


def test_a_restarted_view_graph_never_attaches_to_the_keyframes_of_the_first(observations):
    """The matcher restarts mid-capture and numbers its keyframes from 0 again: they are new
    keyframes of the map (before: ignored as known ids, and the new edges joined the old
    keyframes of the same ids), every edge joins the keyframes it was made between, and the
    second half's frames are localized."""
    session, expected = MapSession(), set()
    first = _feed(session, observations[:25], expected)
    second = _feed(session, observations[25:], expected)
    mapper = session.mapper
    assert first >= 3 and second >= 3
    assert len(mapper.keyframes) == first + second
    made = _edges_by_stamp(mapper)
    assert made <= expected and len(made) >= 0.9 * len(expected)
    late = {obs.stamp_ns for obs in observations[25:]}
    assert any(stamp in late for pair in made for stamp in pair)
    assert len(set(mapper.frame_poses()) & late) >= 10


def test_a_view_graph_continues_a_loaded_map_without_id_collisions(observations, tmp_path):
    """load_map_on_start: the map holds keyframes 0..n-1, the matcher starts at 0."""
    first_session, expected = MapSession(), set()
    first = _feed(first_session, observations[:25], expected)
    path = save_map(first_session.mapper, tmp_path / 'room.rfm')
    session = MapSession()
    session.load(path)
    second = _feed(session, observations[25:], expected)
    assert len(session.mapper.keyframes) == first + second
    assert _edges_by_stamp(session.mapper) <= expected
    assert min(k for k in session.mapper.keyframes if session.mapper.keyframes[k].stamp_ns
               >= observations[25].stamp_ns) >= first


def test_huge_keyframe_ids_get_small_map_ids_and_the_map_saves(observations, tmp_path):
    """A keyframe id >= 2^63 (the message's uint64 allows it) killed the mapper's autosave."""
    session = MapSession()
    ids = [2 ** 64 - 3, 2 ** 64 - 2, 2 ** 64 - 1]
    for k, obs in zip(ids, observations[::10]):
        assert session.add_keyframe(k, obs)
    assert not session.add_keyframe(ids[-1], observations[20])        # the same keyframe again
    assert len(session.mapper.keyframes) == 3 and max(session.mapper.keyframes) < MAX_KEYFRAME_ID
    fresh = Mapper()
    load_map(fresh, save_map(session.mapper, tmp_path / 'big.rfm'))
    assert sorted(fresh.keyframes) == sorted(session.mapper.keyframes)
    np.testing.assert_array_equal([fresh.keyframes[k].stamp_ns for k in sorted(fresh.keyframes)],
                                  [o.stamp_ns for o in observations[::10][:3]])


def test_a_tracked_frame_that_arrives_before_its_keyframe_waits_for_it(observations):
    """Keyframes and tracked frames travel on different topics: a frame may come first."""
    graph, session = ViewGraphBuilder(), MapSession()
    held = []
    for obs in observations[:12]:
        keyframe, edges, track = graph.add(obs)
        if keyframe is not None and keyframe.keyframe_id > 0:
            held.append((keyframe, edges))               # the keyframe is late
        elif keyframe is not None:
            session.add_keyframe(keyframe.keyframe_id, keyframe.observations)
        if track is not None:
            session.add_frame(track)
    logged = session.counts['frames']
    assert held and session.pending_frames
    for keyframe, edges in held:
        session.add_keyframe(keyframe.keyframe_id, keyframe.observations)
        for e in edges:
            session.add_edge(EdgeRecord.from_edge(e))
    assert not session.pending_frames and session.counts['frames'] > logged
    session.update(force_full=True)
    assert len(session.mapper.frame_poses()) == session.counts['frames'] == 12


def test_gaps_in_the_matchers_numbering_are_counted():
    check = SequenceCheck()
    assert [check.add(9, s) for s in (1, 2, 5, 6)] == [0, 0, 2, 0] and check.lost == 2
    assert check.add(9, 6) == 0 and check.add(0, 0) == 0                    # a repeat; unnumbered
    assert [check.add(10, s) for s in (1, 3)] == [0, 1] and check.lost == 3  # a new session
    assert check.add(10, 1) == 0 and check.add(10, 2) == 0                   # restarted, same id
