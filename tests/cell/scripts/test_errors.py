"""Every class of load error names file:line:column and what was expected."""

import pytest

from cell.scripts import CyflexBlock, ScriptError, load_script

F = "[formulas]\npublic y\n"  # a .fdv prefix: the statement under test is on line 3
L = "x none 3 0 MED OFF 1.0\n"  # a .labels header: the expression under test is on line 2
LABELS = "y none 3 0 MED OFF 1.0\n1\n"


@pytest.mark.parametrize(
    "name,text,where,needle",
    [
        # .fdv
        ("a.fdv", F + "y = foo(x)\n", "3:5", "unknown function 'foo'; known: pow, abs"),
        ("a.fdv", F + "y = x $ 2\n", "3:7", "unexpected character '$'"),
        ("a.fdv", F + "y = (x + 2\n", "3:11", "expected ')' to close '(' opened at 3:5, got end"),
        ("a.fdv", F + "y = pow(x, 2\n", "3:13", "expected ')' or ','"),
        ("a.fdv", "[setup]\n" + F + "y = 1\n", "1:2", "unknown section [setup]; expected [init]"),
        ("a.fdv", "dim a\n" + F, "1:1", "a statement before any section"),
        ("a.fdv", F + "z = 1\n", "3:1", "z is not declared; add 'dim z'"),
        ("a.fdv", F + "y = pow(1)\n", "3:5", "pow takes 2 arguments, got 1"),
        ("a.fdv", F + "y = 1 < 2 < 3\n", "3:11", "comparisons do not chain"),
        ("a.fdv", F + "y = 1e999\n", "3:5", "number '1e999' is too large"),
        ("a.fdv", F + "y = 4e\n", "3:5", "bad number '4e'"),
        ("a.fdv", F + "y = x = 2\n", "3:7", "use '==' to compare"),
        ("a.fdv", F + "y = \\\n", "3:5", "continues past the end of the file"),
        ("a.fdv", "[init]\ndim a\na = x\n" + F + "y = a\n", "3:5", "cannot read input channel x"),
        ("a.fdv", "[init]\ndim a\na = 1/0\n" + F + "y = a\n", "3:1",
         ("[init] failed: a (line 3:1): "
         "division by zero")),
        ("a.fdv", "// rate: FAST\n" + F + "y = 1\n", "1:10", "bad rate 'FAST'"),
        ("a.fdv", F + "y = 1 ^ 2\n", "3:7", "use pow(a, b)"),
        ("a.fdv", F + "y = @pow(1,2)\n", "3:5", "unexpected character '@'"),
        ("a.fdv", F + "dim d\ndim d\ny = 1\n", "4:5", "d is already declared with dim at line 3"),
        ("a.fdv", F + "y = max\n", "3:5", "'max' is a function; call it as max(...)"),
        ("a.fdv", F + "y = 4[none]\n", "3:6", "belong to the CyFlex-style .labels dialect"),
        ("a.fdv", F + "dim\n", "3:4", "expected a name after dim"),
        ("a.fdv", F + "y + 1\n", "3:1", "expected a statement"),
        ("a.fdv", "[init]\ndim a\n", "2:1", "no [formulas] section"),
        # .labels
        ("a.labels", L + "[none] * 3\n", "2:1", "a unit annotation [none] must follow a number"),
        ("a.labels", L + "@foo(2,3)\n", "2:1", "unknown function '@foo'; known: @pow"),
        ("a.labels", L + "pow(2,3)\n", "2:1", "did you mean @pow?"),
        ("a.labels", L + "10[rpm] + 2[kPa]\n", "2:9", "cannot add [rpm] and [kpa] outside braces"),
        ("a.labels", L + "10[rpm] - 2[kPa]\n", "2:9", "cannot subtract [rpm] and [kpa]"),
        ("a.labels", "x rpm 3 0 MED OFF 1.0\n 2[kPa] * 3\n", "2:2", ("declared in [rpm] but its "
         "expression is in [kpa]")),
        ("a.labels", L + "{1 + 2\n", "2:7", "expected '}' to close '{' opened at 2:1"),
        ("a.labels", L + "1[none\n", "2:2", "malformed unit annotation"),
        ("a.labels", L + "a_x.FOO\n", "2:5", "unknown running-average statistic .FOO"),
        ("a.labels", L + "a.b\n", "2:3", "statistic .b (attribute access"),
        ("a.labels", L + "a.\n", "2:2", "attribute access"),
        ("a.labels", "x none 3 0 MED OFF\n1\n", "1:1", ("bad label header: expected 7 fields "
         "'Label units format initial_value interval hst_flag tolerance', got 6")),
        ("a.labels", "x none 3 0 FAST OFF 1.0\n1\n", "1:12", ("bad interval 'FAST'; expected FAS, "
         "MED or SLO")),
        ("a.labels", "x none 3 zero MED OFF 1.0\n1\n", "1:10", "bad initial_value 'zero'"),
        ("a.labels", "x none three 0 MED OFF 1.0\n1\n", "1:8", "bad format 'three'"),
        ("a.labels", "x none 3 0 MED maybe 1.0\n1\n", "1:16", "bad hst_flag 'maybe'"),
        ("a.labels", "x none 3 0 MED OFF 1.0\n", "1:1", "label x has no expression line"),
        ("a.labels", L + L + "1\n", "1:1", "no expression line before the next label header"),
        ("a.labels", L + "1\n" + L + "2\n", "3:1", "label x is already defined at line 1"),
        ("a.txt", "x", "1:1",
         "unknown script dialect '.txt'; known suffixes: .fdv, .labels, .ravg"),
    ],
)
def test_load_error_message_has_file_line_column(name, text, where, needle):
    with pytest.raises(ScriptError) as info:
        load_script(name, text)
    err = info.value
    assert str(err).startswith(f"{name}:{where}: "), str(err)
    assert needle in err.message, err.message
    line, col = where.split(":")
    assert (err.line, err.column, err.file) == (int(line), int(col), name)
    assert err.as_dict()["line"] == int(line)
    assert isinstance(err, ValueError)


@pytest.mark.parametrize(
    "ravg,where,needle",
    [
        ("x 1 MED\n", "1:1", "expected 4 fields 'in_variable samples rate statistical_variable'"),
        ("x one MED a_x\n", "1:3", "bad samples 'one'"),
        ("x 0 MED a_x\n", "1:3", "bad samples '0'"),
        ("x 1 FAST a_x\n", "1:5", "bad rate 'FAST'; expected FAS, MED or SLO"),
        ("x 1 MED a.x\n", "1:9", "bad statistical_variable 'a.x'"),
        ("# c\nx 1 MED a_x.\nx 1 MED a_x\n", "3:9", "a_x is already defined at line 2"),
        ("x( 1 MED a_x\n", "1:1", "bad in_variable"),
    ],
)
def test_ravg_errors_name_the_ravg_file(ravg, where, needle):
    with pytest.raises(ScriptError) as info:
        load_script("set.labels", LABELS, ravg)
    assert str(info.value).startswith(f"set.ravg:{where}: "), str(info.value)
    assert needle in info.value.message


def test_several_errors_are_collected_in_one_load():
    text = "[formulas]\npublic y\ny = foo(1)\ny = (2\ny = 3 $ 4\ny = 1\n"
    with pytest.raises(ScriptError) as info:
        load_script("many.fdv", text)
    errs = info.value.errors
    assert [(e.line, e.column) for e in errs] == [(3, 5), (4, 7), (5, 7)]
    assert info.value.report().count("many.fdv:") == 3


def test_collection_is_capped():
    text = "[formulas]\npublic y\n" + "y = $\n" * 500
    with pytest.raises(ScriptError) as info:
        load_script("capped.fdv", text)
    assert 1 < len(info.value.errors) <= 50


def test_unit_checks_pass_inside_braces_and_for_bare_numbers():
    ok = CyflexBlock("u.labels", "x rpm 3 0 MED OFF 1.0\n{2[kPa] + 3[rpm]}\n"
                     "z rpm 3 0 MED OFF 1.0\n2 * x / 3 + 1\n")
    assert ok.units == {"x": "rpm", "z": "rpm"}
