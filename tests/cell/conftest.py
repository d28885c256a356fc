"""Fixtures shared by the tests of seed 002's design tool (``tests/cell/design``) and of its
experiment (``tests/cell/experiments``): one design log and one design file per session."""

import argparse
import json

import pytest

from cell.design import diesel_airpath as D
from cell.sim import write_log

#: A short run that still holds three stationary segments of the etc cycle.
DESIGN_S = 300.0


def design_args(log, out, **kw) -> argparse.Namespace:
    """The options of ``testcell design bias LOG --out OUT`` (and ``states``, ``approach``,
    ``dim``)."""
    return argparse.Namespace(log=str(log), states=kw.get("states"), approach=kw.get("approach", 2),
                              out=str(out), dim=kw.get("dim"))


@pytest.fixture(scope="session")
def design_log(tmp_path_factory):
    """A 300 s ``etc`` log of the large diesel, with the P_EM sensor."""
    path = tmp_path_factory.mktemp("bias") / "etc.log"
    write_log(path, "etc", seed=0, duration=DESIGN_S, progress=False)
    return path


@pytest.fixture(scope="session")
def design(design_log, tmp_path_factory):
    """The design file of :func:`design_log` (Approach 2): its contents and its path."""
    out = tmp_path_factory.mktemp("design") / "bias_design.json"
    assert D.main(design_args(design_log, out)) == 0
    return json.loads(out.read_text()), out
