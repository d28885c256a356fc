"""Random expressions evaluate as Python would on the same numbers (hypothesis)."""

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cell.scripts import FdvBlock

VARS = ("a", "b", "c")
UNARY = ("abs", "sqrt", "exp", "log", "log10", "sin", "cos", "tan")
PREC = {"or": 1, "and": 2, "not": 3, "cmp": 4, "+": 5, "-": 5, "*": 6, "/": 6, "neg": 7}

numbers = st.one_of(
    st.integers(0, 20).map(float),
    st.floats(0.0, 1e6, allow_nan=False, allow_infinity=False),
    st.sampled_from([0.5, 1e-6, 4e-6, 2.5e10]),
)
leaves = st.one_of(numbers.map(lambda v: ("num", v)),
                   st.sampled_from(VARS).map(lambda n: ("var", n)))


def _extend(children, logic):
    ops = [
        st.tuples(st.just("neg"), children),
        st.tuples(st.just("bin"), st.sampled_from("+-*/"), children, children),
        st.tuples(st.just("call"), st.sampled_from(UNARY), st.tuples(children)),
        st.tuples(st.just("call"), st.just("pow"), st.tuples(children, children)),
        st.tuples(st.just("call"), st.sampled_from(("min", "max")),
                  st.lists(children, min_size=2, max_size=3).map(tuple)),
        st.tuples(st.just("cmp"), st.sampled_from(["<", "<=", ">", ">=", "==", "!=", "<>"]),
                  children, children),
    ]
    if logic:
        ops += [
            st.tuples(st.sampled_from(("and", "or")), children, children),
            st.tuples(st.just("not"), children),
            st.tuples(st.just("call"), st.just("if"), st.tuples(children, children, children)),
            st.tuples(st.just("call"), st.just("limit"), st.tuples(children, children, children)),
        ]
    return st.one_of(*ops)


full_trees = st.recursive(leaves, lambda ch: _extend(ch, True), max_leaves=12)
python_trees = st.recursive(leaves, lambda ch: _extend(ch, False), max_leaves=12)


def prec(node):
    kind = node[0]
    if kind in ("num", "var", "call"):
        return 8
    if kind == "bin":
        return PREC[node[1]]
    return PREC[kind]


def render(node, need=0):
    """Script text with only the parentheses our grammar (and Python's) needs."""
    kind = node[0]
    if kind == "num":
        text = repr(node[1])
    elif kind == "var":
        text = node[1]
    elif kind == "neg":
        text = "- " + render(node[1], 7)
    elif kind == "not":
        text = "not " + render(node[1], 3)
    elif kind == "bin":
        p = PREC[node[1]]
        text = f"{render(node[2], p)} {node[1]} {render(node[3], p + 1)}"
    elif kind == "cmp":
        text = f"{render(node[2], 5)} {node[1]} {render(node[3], 5)}"
    elif kind in ("and", "or"):
        p = PREC[kind]
        text = f"{render(node[1], p)} {kind} {render(node[2], p + 1)}"
    else:
        text = f"{node[1]}({', '.join(render(a) for a in node[2])})"
    return f"({text})" if prec(node) < need else text


FUNCS = {f: getattr(math, f) for f in ("sqrt", "exp", "log", "log10", "sin", "cos", "tan", "pow")}
FUNCS.update(abs=math.fabs, min=min, max=max)
CMP = {"<": float.__lt__, "<=": float.__le__, ">": float.__gt__, ">=": float.__ge__,
       "==": float.__eq__, "!=": float.__ne__, "<>": float.__ne__}


def reference(node, env):
    """Plain Python on floats, written independently of the compiler."""
    kind = node[0]
    if kind == "num":
        return node[1]
    if kind == "var":
        return env[node[1]]
    if kind == "neg":
        return -reference(node[1], env)
    if kind == "not":
        return 0.0 if reference(node[1], env) else 1.0
    if kind == "bin":
        a, b = reference(node[2], env), reference(node[3], env)
        return {"+": a + b, "-": a - b, "*": a * b}[node[1]] if node[1] != "/" else a / b
    if kind == "cmp":
        return 1.0 if CMP[node[1]](float(reference(node[2], env)),
                                   float(reference(node[3], env))) else 0.0
    if kind == "and":
        return 1.0 if (reference(node[1], env) and reference(node[2], env)) else 0.0
    if kind == "or":
        return 1.0 if (reference(node[1], env) or reference(node[2], env)) else 0.0
    f, args = node[1], node[2]
    if f == "if":
        return reference(args[1], env) if reference(args[0], env) else reference(args[2], env)
    vals = [reference(a, env) for a in args]
    if f == "limit":
        return min(max(vals[0], vals[1]), vals[2])
    return FUNCS[f](*vals)


def check(text, expect, env):
    """Compile ``y = text`` and compare with ``expect()`` (a value or a raised error)."""
    block = FdvBlock("prop.fdv", f"[formulas]\npublic y\ny = {text}\n")
    try:
        want = float(expect())
    except (ArithmeticError, ValueError):
        want = math.nan
    got = block.step(0.0, {n: env[n] for n in block.inputs})["y"]
    if math.isfinite(want):
        assert got == want, (text, got, want)
        assert not block.errors
    else:
        assert math.isnan(got), (text, got, want)
        assert "y" in block.errors


env_values = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
envs = st.fixed_dictionaries({n: env_values for n in VARS})
fast = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@fast
@given(full_trees, envs)
def test_random_expressions_match_a_python_reference(tree, env):
    check(render(tree), lambda: reference(tree, env), env)


@fast
@given(python_trees, envs)
def test_arithmetic_text_means_what_python_parses(tree, env):
    """The same text, parsed by Python itself, gives the same number (precedence, signs)."""
    text = render(tree)
    py = text.replace("<>", "!=")
    namespace = {"__builtins__": {}, **FUNCS, **env}
    check(text, lambda: eval(py, namespace), env)
