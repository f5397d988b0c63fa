"""experiments/interpolate.py, which builds the shipped model from its last phases: the
weight-space line between two parameter trees, and the parameters it keeps from the start."""

import importlib.util
import os

import numpy as np
import pytest

_PATH = os.path.join(os.path.dirname(__file__), "..", "experiments", "interpolate.py")
_spec = importlib.util.spec_from_file_location("interpolate", _PATH)
interpolate_module = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(interpolate_module)
interpolate = interpolate_module.interpolate

START = {"box0_w": np.array([[1.0, 2.0], [3.0, 4.0]]), "mlp": {"kernel": np.array([0.0, -2.0])}}
TUNED = {"box0_w": np.array([[3.0, 2.0], [1.0, 0.0]]), "mlp": {"kernel": np.array([4.0, 2.0])}}


@pytest.mark.parametrize("alpha", [0.0, 0.25, 1.0])
def test_every_leaf_lies_on_the_line(alpha):
    got = interpolate(START, TUNED, alpha)
    # hand-computed: (1 - a) * start + a * tuned
    want_box = {0.0: [[1.0, 2.0], [3.0, 4.0]], 0.25: [[1.5, 2.0], [2.5, 3.0]],
                1.0: [[3.0, 2.0], [1.0, 0.0]]}[alpha]
    want_mlp = {0.0: [0.0, -2.0], 0.25: [1.0, -1.0], 1.0: [4.0, 2.0]}[alpha]
    np.testing.assert_allclose(got["box0_w"], want_box)
    np.testing.assert_allclose(got["mlp"]["kernel"], want_mlp)


def test_kept_parameters_stay_the_starts():
    got = interpolate(START, TUNED, 1.0, keep=("mlp",))
    np.testing.assert_array_equal(got["mlp"]["kernel"], START["mlp"]["kernel"])
    np.testing.assert_array_equal(got["box0_w"], TUNED["box0_w"])
