"""The limits every source's frames are held to (`frame.drop_beyond_limits`)."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen_jax.frame import MAX_SIZE_M, MAX_SPEED_MPS, Frame, drop_beyond_limits
from scenegen_jax.vector_map import VectorMap


def _frame(size, velocity, ego_size=(2.0, 4.5), ego_velocity=(5.0, 0.0)) -> Frame:
    n = len(size)
    return Frame(
        scene_id="log/7", source="f.json", cls=np.zeros(n, np.int32),
        position=np.arange(2 * n, dtype=float).reshape(n, 2), size=np.asarray(size, float),
        heading=np.zeros(n), velocity=np.asarray(velocity, float),
        track_id=np.array([f"t{i}" for i in range(n)]), ego_velocity=np.asarray(ego_velocity),
        ego_size=np.asarray(ego_size, float), map=VectorMap(),
    )


def test_rows_beyond_the_limits_are_dropped_and_counted():
    big, fast = MAX_SIZE_M + 0.1, MAX_SPEED_MPS + 0.1
    frame = _frame(
        size=[(2, 4.5), (2, big), (2, 4.5), (big, 4), (2, MAX_SIZE_M)],
        # 3-4-5: speed 100 exactly is kept; 60, 80.1 -> 100.06 is dropped; big and fast: size.
        velocity=[(3, 4), (0, 0), (60, 80.1), (0, fast), (60, 80)],
    )
    kept, drops = drop_beyond_limits(frame)
    assert drops == {"invalid:size": 2, "invalid:speed": 1}
    assert kept.track_id.tolist() == ["t0", "t4"]
    np.testing.assert_array_equal(kept.position, [[0, 1], [8, 9]])
    assert len(kept.cls) == len(kept.heading) == len(kept.velocity) == len(kept.size) == 2
    same, none = drop_beyond_limits(kept)
    assert same is kept and not none


def test_an_ego_beyond_the_limits_is_named():
    with pytest.raises(ValueError,
                       match=r"^f\.json: scene log/7: ego width/length: \[2\.0, 31\.0\]"):
        drop_beyond_limits(_frame([], np.zeros((0, 2)), ego_size=(2.0, 31.0)))
    with pytest.raises(ValueError, match=r"^f\.json: scene log/7: ego velocity: speed inf m/s"):
        drop_beyond_limits(_frame([], np.zeros((0, 2)), ego_velocity=(np.inf, 0.0)))


def test_an_ego_beyond_the_world_range_is_named_in_every_source():
    """Relative positions taken near 1e300 m round to 0 (every actor at the ego): an ego
    whose world position (`city_from_ego`) is beyond MAX_WORLD_M makes the scene an error,
    whichever reader made the frame."""
    import warnings

    from scenegen_jax.frame import MAX_WORLD_M

    far = _frame([(2, 4.5)], [(0, 0)])
    far.city_from_ego = np.array([[1.0, 0, 1e300], [0, 1, 1e300], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"^f\.json: scene log/7: ego position: \(1e\+300, "
                       r"1e\+300\) m in the world frame, beyond 1e\+07 m$"):
        drop_beyond_limits(far)
    far.city_from_ego[:2, 2] = (-MAX_WORLD_M, MAX_WORLD_M)  # at the limit: a place
    assert drop_beyond_limits(far)[0] is far
    with warnings.catch_warnings():  # speeds near 1e308: counted, no overflow warning
        warnings.simplefilter("error")
        fast = _frame([(2, 4.5)], [(1e308, 1e308)])
        assert drop_beyond_limits(fast)[1] == {"invalid:speed": 1}
        with pytest.raises(ValueError, match=r"ego velocity: speed 1\.414e\+308 m/s"):
            drop_beyond_limits(_frame([], np.zeros((0, 2)), ego_velocity=(1e308, 1e308)))
