"""README.md starts with the two set-up commands, the test one sets up and runs the whole suite,
CI runs it, and the README stays short: at most 150 lines, the rest in docs/, every docs/ link
pointing at a file."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    title, rest = text.split("```bash\n", 1)
    assert [line for line in title.splitlines() if line.strip()] == ["# vservo"], "only the title comes before the commands"
    block = rest.split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def test_readme_opens_with_the_main_job_and_the_test_command():
    main_job, tests = readme_commands()
    assert main_job.startswith("pip install -c constraints.txt") and "vservo" in main_job
    assert tests == "bash tests/run.sh"  # which sets up, then runs pytest with its arguments:
    run = (ROOT / "tests" / "run.sh").read_text().splitlines()
    install = (ROOT / "tests" / "install.sh").read_text().splitlines()
    assert run.index("bash tests/install.sh") < run.index('exec python -m pytest -n 2 --dist loadfile "$@"')
    assert "python -m pip install -c constraints.txt -e '.[test]'" in install
    assert any("apt-get install" in line and "chromium" in line for line in install)


def test_ci_runs_the_readme_test_command():
    _, tests = readme_commands()
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests in ci.splitlines()


def test_torch_is_pinned_to_the_local_cpu_build():
    constraints = (ROOT / "constraints.txt").read_text().splitlines()
    assert "torch==2.13.0" in constraints
    assert any(line.startswith("viser==") for line in constraints)


def test_readme_is_at_most_150_lines():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


def test_every_docs_link_in_the_readme_points_to_a_file():
    links = re.findall(r"\]\((docs/[^)#\s]+)", (ROOT / "README.md").read_text())
    assert links, "the README links into docs/"
    missing = [link for link in links if not (ROOT / link).is_file()]
    assert missing == []
