"""``python -m dinerdash evaluate`` starts on the evaluation seeds (1000..) unless told
otherwise, ``--help`` of ``evaluate`` and ``collect`` shows the defaults, and every ``--help``
says whole sentences."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from dinerdash.cli import main


def test_evaluate_defaults_to_the_evaluation_seeds(
    address: str, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["evaluate", "--episodes", "2", "--max-steps", "20", "--json", "--address", address]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "(seeds 1000..=1001)" in out
    assert json.loads(out.strip().splitlines()[-1])["seed"] == 1000


@pytest.mark.parametrize(
    ("command", "shown"),
    [
        ("evaluate", ["(default: 1000)", "(default: 100)", "(default: expert)"]),
        ("collect", ["(default: 0)", "(default: 274)", "below the evaluation seeds 1000..1099"]),
        ("bench", ["(default: 20000)", "(default: 256)", "(default: 3)"]),
        ("watch", ["(default: 0)"]),
    ],
)
def test_help_shows_the_defaults(
    command: str, shown: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for words in shown:
        assert words in text, words
    assert "(default: None)" not in text and "(default: False)" not in text


@pytest.mark.parametrize("module", ["dinerdash", "dinerdash_agents"])
def test_help_says_whole_sentences(module: str) -> None:
    """The description is the module docstring's whole first paragraph, not its first line cut
    mid-sentence ("measure speed,")."""
    out = subprocess.run(
        [sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60
    ).stdout
    description = " ".join(out.split("\n\n")[1].split())
    assert description.endswith(".") and "``" not in description, description
