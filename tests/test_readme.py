"""The README's five-line library example runs as printed and gives what its comments say."""

import re
from pathlib import Path

import numpy as np
import pytest

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


@pytest.mark.slow  # about a minute of simulation on the 2 CI cores; run with -m slow
def test_five_line_library_example(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    assert len(blocks) == 1
    code = blocks[0]
    assert len([line for line in code.splitlines() if line.strip()]) <= 5
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102
    result, x_hand = namespace["result"], namespace["x_hand"]
    exp = result.config
    assert exp.seeds == 3 and exp.task.swings == 2 and exp.task.learner.mu == 2e-3
    assert x_hand.shape == (3, 2, 3000, 2)  # (seeds, swings, steps, 2)
    peaks = {c: result.metrics[c]["peak_force"]["mean"] for c in ("plain", "learned")}
    assert peaks["learned"] < peaks["plain"]  # what the figure shows
    assert np.all(np.isfinite(x_hand))
    assert "mean" in capsys.readouterr().out
