"""Hostile scripts get a load error or bounded work: never Python execution or a hang."""

import math

import pytest

from cell.scripts import FdvBlock, ScriptError, load_script
from cell.scripts.expr import MAX_DEPTH
from cell.scripts.source import MAX_SOURCE_CHARS

F = "[formulas]\npublic y\n"
LAB = "y none 3 0 MED OFF 1.0\n"


@pytest.mark.parametrize(
    "name,text",
    [
        ("h.fdv", F + "y = __import__('os')\n"),
        ("h.fdv", F + "y = __import__(1)\n"),
        ("h.fdv", F + "y = open(1)\n"),
        ("h.fdv", F + "y = eval(1)\n"),
        ("h.fdv", F + "y = a.b\n"),
        ("h.fdv", F + "y = x.__class__\n"),
        ("h.fdv", F + "y = (1).__class__\n"),
        ("h.fdv", F + "y = x[0]\n"),
        ("h.fdv", F + "y = lambda: 1\n"),
        ("h.fdv", F + "y = 'text'\n"),
        ("h.fdv", F + "y = 1; import os\n"),
        ("h.fdv", F + "y = [i for i in x]\n"),
        ("h.fdv", F + "y = x if x else 1\n"),
        ("h.fdv", F + "y = _pow(1, 2)\n"),
        ("h.labels", LAB + "@__import__(1)\n"),
        ("h.labels", LAB + "a_x_lm.FV.__class__\n"),
        ("h.labels", LAB + "a.__class__\n"),
        ("h.labels", LAB + "x[0]\n"),
    ],
)
def test_no_way_into_python(name, text):
    with pytest.raises(ScriptError):
        load_script(name, text)


def test_deep_nesting_is_refused_quickly():
    for text in ("(" * 10_000 + "1" + ")" * 10_000, "-" * 10_000 + "1",
                 "pow(" * 5_000 + "1" + ", 2)" * 5_000, "not " * 10_000 + "1",
                 "+".join(["1"] * 10_000)):
        with pytest.raises(ScriptError, match=f"more than {MAX_DEPTH} levels"):
            load_script("deep.fdv", F + "y = " + text + "\n")
    with pytest.raises(ScriptError, match="levels"):
        load_script("deep.labels", LAB + "{" * 10_000 + "1" + "}" * 10_000 + "\n")


def test_nesting_at_the_limit_still_compiles_and_runs():
    depth = MAX_DEPTH - 2
    block = load_script("ok.fdv", F + "y = " + "abs(" * depth + "x" + ")" * depth + "\n")
    assert block.step(0.0, {"x": -2.0}) == {"y": 2.0}
    chain = "x" + " + 1" * (MAX_DEPTH - 1)
    block = load_script("ok.fdv", F + "y = " + chain + "\n")
    assert block.step(0.0, {"x": 0.0}) == {"y": float(MAX_DEPTH - 1)}


def test_megabytes_are_refused_before_parsing():
    for text in (F + "y = 1\n" * 500_000, "x" * (3 * 1024 * 1024), F + "y = " + "1+" * 10**6 + "1"):
        with pytest.raises(ScriptError, match=f"limit is {MAX_SOURCE_CHARS}"):
            load_script("big.fdv", text)
    with pytest.raises(ScriptError, match="limit"):
        load_script("big.labels", LAB + "1\n", "x 1 MED a\n" * 300_000)


def test_python_names_are_just_channels_and_locals():
    text = ("[init]\ndim __builtins__\ndim None\n__builtins__ = 2\n"
            "[formulas]\npublic import\npublic lambda\n"
            "import = __builtins__ * __class__\nlambda = None + print\n")
    block = FdvBlock("names.fdv", text)
    assert block.inputs == ["__class__", "print"]
    assert block.outputs == ["import", "lambda"]
    assert block.step(0.0, {"__class__": 3.0, "print": 1.0}) == {"import": 6.0, "lambda": 1.0}
    assert block._run.__globals__["__builtins__"] == {}


def test_non_string_text_is_refused():
    with pytest.raises(ScriptError, match="must be a string"):
        load_script("x.fdv", b"[formulas]\n")


@pytest.mark.parametrize("number", ["1e309", "9" * 5000, "1" + "0" * 400])
def test_huge_constants_are_a_load_error_at_their_position(number):
    with pytest.raises(ScriptError, match=r"h\.fdv:3:5: number .* is too large"):
        load_script("h.fdv", F + "y = " + number + "\n")


@pytest.mark.parametrize("expr", ["1e308 * 10", "pow(10, 400)", "exp(1e6)", "-1e308 * 1e10",
                                  "1e308 + 1e308", "sqrt(-1)", "log(0)"])
def test_overflow_at_run_time_marks_the_output_invalid_never_raises(expr):
    block = load_script("h.fdv", F + "y = " + expr + "\n")
    out = block.step(0.0, {})
    assert math.isnan(out["y"]) and "y" in block.errors, (out, block.errors)
