"""The README's quick start and .ci/run must not drift apart."""
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _quick_start_commands():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Quick start.*?```bash\n(.*?)```", text, re.S)
    assert block, "README.md has no quick-start bash block"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_quick_start_has_two_commands():
    cmds = _quick_start_commands()
    assert len(cmds) == 2
    assert "hbvm-md demo" in cmds[0]
    assert "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert _quick_start_commands()[1] in ci


def _python_blocks():
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)


def test_readme_api_snippet_runs_and_prints_its_claims(capsys):
    blocks = _python_blocks()
    api = next(b for b in blocks if "# 1. The core engine" in b)
    exec(compile(api, "README.md (Public API)", "exec"), {})
    out = capsys.readouterr().out
    # each printed energy error is at round-off, as the README says (the REBOUND run prints its
    # final error, which can be exactly 0.0)
    errors = [float(x) for x in re.findall(r"(?:=|:|error) (\d\.\d+e-\d+|0\.0)\b", out)]
    assert len(errors) == 4 and max(errors) < 1e-12, out


def test_readme_own_hamiltonian_example_prints_a_round_off_error(capsys):
    block = next(b for b in _python_blocks() if "class Oscillator" in b)
    exec(compile(block, "README.md (own Hamiltonian)", "exec"), {})
    out = capsys.readouterr().out
    assert out.startswith("oscillator, 1000 steps: max |H-H0|/|H0| =")
    assert float(out.split("=")[-1]) < 1e-13
