"""The suite's ``--rules-before`` option (tests/conftest.py): a test's rule-before half runs only when asked."""
from pathlib import Path

pytest_plugins = ["pytester"]

CONFTEST = Path(__file__).with_name("conftest.py")

CASE = '''
def test_a_rule(rules_before):
    assert 1 + 1 == 2                   # the rule's own check
    if not rules_before:
        return
    raise AssertionError("the half with the rule switched off ran")
'''


def test_the_rule_before_half_runs_only_with_the_option_and_the_summary_counts_the_tests_that_stopped(pytester):
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makepyfile(CASE)
    plain = pytester.runpytest("-p", "no:cacheprovider")
    plain.assert_outcomes(passed=1)
    plain.stdout.fnmatch_lines(["1 diagnose tests checked their rule but not that their case still needs it*"])
    asked = pytester.runpytest("-p", "no:cacheprovider", "--rules-before")
    asked.assert_outcomes(failed=1)
    assert "checked their rule but not" not in asked.stdout.str()
