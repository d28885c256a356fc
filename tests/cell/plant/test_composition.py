"""Plants wired by signal name (cell/plant/composition.py), with small plants written here."""

from __future__ import annotations

import pytest

from cell.core.errors import ConfigError
from cell.plant import Composition, Plant


class Counter(Plant):
    """Counts its steps; outputs the count and the time of its last step."""

    def __init__(self, name: str, period: float, out: str, inp: str | None = None) -> None:
        super().__init__(name, period)
        self.outputs = (out, f"{out}_T")
        self.inputs = (inp,) if inp else ()
        self.n = 0
        self.t = 0.0
        self.seen: list[float | None] = []

    def step(self, t, u):
        self.n += 1
        self.t = t
        self.seen.append(u.get(self.inputs[0]) if self.inputs else None)

    def output(self):
        return {self.outputs[0]: float(self.n), self.outputs[1]: self.t}


def test_each_plant_steps_at_its_own_period():
    fast, slow = Counter("fast", 0.01, "A"), Counter("slow", 0.05, "B")
    comp = Composition("two-rates", [fast, slow])
    assert comp.dt == 0.01
    comp.run(1.0)
    assert (fast.n, slow.n) == (100, 20)
    assert comp["B_T"] == pytest.approx(1.0) and comp["A_T"] == pytest.approx(1.0)


def test_a_later_plant_sees_an_earlier_plants_output_of_the_same_step():
    a = Counter("a", 0.01, "A")
    b = Counter("b", 0.01, "B", inp="A")
    comp = Composition("chain", [a, b])
    comp.run(0.03)
    assert b.seen == [1.0, 2.0, 3.0]
    # in the other order, b reads a's output of the step before
    a2, b2 = Counter("a", 0.01, "A"), Counter("b", 0.01, "B", inp="A")
    Composition("chain", [b2, a2]).run(0.03)
    assert b2.seen == [0.0, 1.0, 2.0]


def test_two_producers_of_one_signal_are_refused_naming_both():
    with pytest.raises(ConfigError, match="A is produced by both plant one and plant two"):
        Composition("clash", [Counter("one", 0.01, "A"), Counter("two", 0.01, "A")])


def test_periods_must_be_whole_multiples_of_the_fastest():
    with pytest.raises(ConfigError, match="whole multiple"):
        Composition("odd", [Counter("a", 0.01, "A"), Counter("b", 0.015, "B")])


def test_external_inputs_hold_until_set_again_and_are_validated():
    b = Counter("b", 0.01, "B", inp="CMD")
    comp = Composition("ext", [b])
    assert comp.external == {"CMD"}
    comp.step()
    comp.set_input("CMD", 2.5)
    comp.run(0.02)
    assert b.seen == [None, 2.5, 2.5]
    with pytest.raises(ConfigError, match="OTHER is not an input"):
        comp.set_input("OTHER", 1.0)
    with pytest.raises(ConfigError, match="finite"):
        comp.set_input("CMD", float("inf"))
    assert comp["CMD"] == 2.5
