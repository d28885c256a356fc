"""Block parameters: scalars as before, vectors and (diagonal) matrices, JSON in and out."""

import json
import math

import numpy as np
import pytest

from cell.runtime.blocks import Block, Param
from cell.core.errors import ParamError


def refused(param, value):
    with pytest.raises(ParamError) as err:
        param.check(value)
    assert err.value.field == param.name
    return err.value.message


# -- scalars (unchanged) -----------------------------------------------------------------
def test_scalar_params_keep_their_behaviour_and_messages():
    q = Param("Q", float, "", gt=0.0)
    assert q.check(3) == 3.0 and isinstance(q.check(3), float)
    assert refused(q, 0.0) == "must be > 0, got 0.0"
    assert refused(q, math.nan) == "must be finite, got nan"
    assert refused(q, "1") == "must be a number, got str '1'"
    assert refused(q, True) == "must be a number, got bool True"
    n = Param("samples", int, "", ge=1, le=10)
    assert n.check(4.0) == 4 and isinstance(n.check(4.0), int)
    assert refused(n, 2.5) == "must be a whole number, got 2.5"
    assert refused(n, 11) == "must be <= 10, got 11"
    assert refused(n, 0) == "must be >= 1, got 0"
    assert q.dump(2.0) == 2.0


# -- vectors -----------------------------------------------------------------------------
def test_vector_accepts_lists_tuples_and_arrays():
    x0 = Param("x0", float, "", shape="vector", size=3)
    for value in ([1, 2.5, -3], (1, 2.5, -3), np.array([1, 2.5, -3])):
        got = x0.check(value)
        assert isinstance(got, np.ndarray) and got.dtype == float
        np.testing.assert_array_equal(got, [1.0, 2.5, -3.0])
    assert x0.dump(x0.check([1, 2, 3])) == [1.0, 2.0, 3.0]
    assert Param("v", float, "", shape="vector").check([7]).tolist() == [7.0]  # any length


@pytest.mark.parametrize("value,words", [
    ([1.0, 2.0], "must be a list of 3 numbers, got shape 2"),
    ([[1.0, 2.0, 3.0]], "must be a list of 3 numbers, got shape 1x3"),
    (1.0, "must be a list of 3 numbers, got shape scalar"),
    ([], "got shape 0"),
    ([1.0, "2", 3.0], "must be a list of numbers"),
    ([1.0, None, 3.0], "must be a list of numbers"),
    ([1.0, False, 3.0], "must be a list of numbers"),
    ({"a": 1}, "must be a list of numbers"),
    ([1.0, [2.0], 3.0], "equal lengths"),
    ([1.0, math.nan, 3.0], "element [1] must be finite, got nan"),
    ([1.0, 2.0, -math.inf], "element [2] must be finite, got -inf"),
])
def test_vector_refusals_name_the_field_and_the_problem(value, words):
    assert words in refused(Param("x0", float, "", shape="vector", size=3), value)


def test_vector_bounds_apply_per_element_and_may_differ_per_element():
    phi = Param("x0", float, "", shape="vector", size=4, ge=0.0, le=(1.0, 1.0, 1.0, math.inf))
    phi.check([0.0, 0.5, 1.0, 250.0])
    assert refused(phi, [0.0, 1.5, 1.0, 250.0]) == "element [1] must be <= 1, got 1.5"
    assert refused(phi, [0.0, 0.5, 1.0, -2.0]) == "element [3] must be >= 0, got -2.0"
    assert "element [0] must be > 0" in refused(
        Param("x0", float, "", shape="vector", gt=0.0), [0.0, 1.0])


# -- diagonal matrices -----------------------------------------------------------------------
def test_diag_accepts_its_diagonal_a_diagonal_nested_list_or_a_number():
    Q = Param("Q", float, "", shape="diag", size=3, pd=True)
    for value in ([1.0, 2.0, 3.0], [[1, 0, 0], [0, 2, 0], [0, 0, 3]], np.diag([1.0, 2.0, 3.0])):
        np.testing.assert_array_equal(Q.check(value), [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(Q.check(4), [4.0, 4.0, 4.0])  # 4 x identity
    assert Q.dump(Q.check([[1, 0, 0], [0, 2, 0], [0, 0, 3]])) == [1.0, 2.0, 3.0]


@pytest.mark.parametrize("value,words", [
    ([1.0, 2.0], "must be a list of 3 diagonal elements, got shape 2"),
    ([[1, 0.1, 0], [0.1, 2, 0], [0, 0, 3]], "must be diagonal, but element [0][1] is 0.1"),
    ([[1, 0], [0, 2]], "got shape 2x2"),
    ([1.0, 0.0, 3.0], "must be positive definite: diagonal element [1] is 0.0"),
    ([1.0, 2.0, -3.0], "must be positive definite: diagonal element [2] is -3.0"),
    (-1.0, "positive definite"),
    ([1.0, math.inf, 3.0], "diagonal element [1] must be finite, got inf"),
    ([[1, 0, 0], [0, math.nan, 0], [0, 0, 1]], "diagonal element [1] must be finite"),
    ("diag", "must be a list of diagonal elements, got str 'diag'"),
])
def test_diag_refusals_name_the_field_and_the_problem(value, words):
    assert words in refused(Param("Q", float, "", shape="diag", size=3, pd=True), value)


def test_diag_bounds_and_any_size():
    R = Param("R", float, "", shape="diag", ge=1e-12, le=1e6)
    assert R.check([1e-12, 1e6]).tolist() == [1e-12, 1e6]
    assert refused(R, [1.0, 1e7]) == "diagonal element [1] must be <= 1e+06, got 10000000.0"
    assert "one or more" in refused(R, 1.0)  # a number needs a known size


# -- full symmetric matrices -------------------------------------------------------------
def test_matrix_accepts_symmetric_positive_definite_and_gives_nested_lists():
    P = Param("P0", float, "", shape="matrix", size=2, pd=True)
    got = P.check([[2.0, 0.5], [0.5, 1.0]])
    assert got.shape == (2, 2)
    assert P.dump(got) == [[2.0, 0.5], [0.5, 1.0]]
    np.testing.assert_array_equal(P.check([3.0, 4.0]), np.diag([3.0, 4.0]))
    np.testing.assert_array_equal(P.check(2.0), 2.0 * np.eye(2))


@pytest.mark.parametrize("value,words", [
    ([[2.0, 0.5], [0.4, 1.0]], "must be symmetric: [0][1] = 0.5 but [1][0] = 0.4"),
    ([[1.0, 2.0], [2.0, 1.0]], "must be positive definite, its smallest eigenvalue is -1"),
    ([[1.0, math.nan], [math.nan, 1.0]], "element [0][1] must be finite, got nan"),
    ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "must be a 2x2 matrix, got shape 3x3"),
    ([[1.0, 0.0], [0.0]], "equal lengths"),
    ([[-1.0, 0.0], [0.0, 1.0]], "diagonal element [0] must be > 0"),
])
def test_matrix_refusals_name_the_field_and_the_problem(value, words):
    assert words in refused(Param("P0", float, "", shape="matrix", size=2, pd=True, gt=0.0), value)


def test_checked_arrays_are_read_only_and_shapes_are_known():
    v = Param("x0", float, "", shape="vector", size=2).check([1.0, 2.0])
    with pytest.raises(ValueError):
        v[0] = 5.0
    with pytest.raises(ValueError, match="shape"):
        Param("Q", float, "", shape="tensor")


# -- blocks --------------------------------------------------------------------------------
class Tunable(Block):
    kind = "tunable"
    PARAMS = {
        "gain": Param("gain", float, "", gt=0.0),
        "Q": Param("Q", float, "", shape="diag", size=2, pd=True),
        "x0": Param("x0", float, "", shape="vector", size=2),
    }

    def __init__(self, **kw):
        super().__init__("tun", ["IN"], ["OUT"], **kw)
        self._apply(self.validate({"gain": 1.0, "Q": [1.0, 2.0], "x0": [0.0, 0.0]}))

    def _step(self, t, inputs):
        return {"OUT": inputs["IN"]}


def test_block_params_are_json_and_round_trip():
    b = Tunable()
    params = b.params()
    assert params == {"gain": 1.0, "Q": [1.0, 2.0], "x0": [0.0, 0.0]}
    again = json.loads(json.dumps(params, allow_nan=False))
    assert b.set_params(again) == params
    assert b.set_params({"Q": 3.0}) == {"gain": 1.0, "Q": [3.0, 3.0], "x0": [0.0, 0.0]}
    json.dumps(b.describe(), allow_nan=False)


def test_block_change_is_all_or_nothing_across_scalars_and_arrays():
    b = Tunable()
    before = b.params()
    with pytest.raises(ParamError) as err:
        b.set_params({"gain": 5.0, "x0": [1.0, 1.0], "Q": [1.0, -1.0]})
    assert err.value.field == "Q"
    assert b.params() == before
    with pytest.raises(ParamError) as err:
        b.set_params({"Q": [9.0, 9.0], "gain": -1.0})
    assert err.value.field == "gain" and b.params() == before


def test_block_units_default_empty_and_can_be_given():
    assert Tunable().units == {}
    assert Tunable(units={"OUT": "mmH2O"}).units == {"OUT": "mmH2O"}
