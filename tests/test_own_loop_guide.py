"""docs/guide/own-loop.md's example runs as written, through the public `capvector` names."""

import re
import runpy
from pathlib import Path

from safetensors.torch import load_file

GUIDE = Path(__file__).resolve().parent.parent / "docs" / "guide" / "own-loop.md"


def test_the_guide_example_runs_and_does_what_it_says(tmp_path, monkeypatch, capsys) -> None:
    code = re.search(r"```python\n(.*?)```", GUIDE.read_text(), re.S).group(1)
    script = tmp_path / "example.py"
    script.write_text(code)
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(script), run_name="__main__")
    pt, ft, ao = (load_file(tmp_path / f"{n}.safetensors") for n in ("pt", "ft", "ao"))
    gamma, meta = load_file(tmp_path / "gamma.safetensors"), load_file(tmp_path / "meta.safetensors")
    for name in pt:
        assert (gamma[name] - (ao[name] - ft[name])).abs().max() < 1e-6, name
        assert (meta[name] - (pt[name] + gamma[name])).abs().max() < 1e-6, name
    printed = capsys.readouterr().out
    assert re.search(r"action loss \d+\.\d+, orthogonal term \d", printed), printed


def test_the_lerobot_style_example_sets_a_relative_lambda(tmp_path, monkeypatch, capsys) -> None:
    first, second = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), re.S)[:2]
    monkeypatch.chdir(tmp_path)
    for i, code in enumerate((first, second)):
        (tmp_path / f"example{i}.py").write_text(code)
        runpy.run_path(str(tmp_path / f"example{i}.py"), run_name="__main__")
    printed = capsys.readouterr().out
    weight = float(re.search(r"relative λ = 0\.1 × ‖∇ loss‖/‖γ‖ = (\S+);", printed).group(1))
    assert 0 < weight < 1e3, printed


def test_importing_capvector_loads_no_torch_until_a_name_is_used() -> None:
    import subprocess
    import sys

    loaded = "print('torch' in sys.modules)"
    probe = f"import sys, capvector; {loaded}; capvector.OrthogonalRegularizer; {loaded}"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "True"]
