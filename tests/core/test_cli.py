import subprocess
import sys
from pathlib import Path

import pytest

from fwk.cli import main

REPO = Path(__file__).resolve().parents[2]


def test_list_shows_every_kind(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for kind in ("dataset", "representation", "model", "metric", "task"):
        assert f" {kind} " in out
    for name in ("pca", "mlp-vae", "euclidean", "l1", "synthetic-heads", "reconstruct"):
        assert name in out


def test_list_unknown_kind_exit_2(capsys):
    assert main(["list", "--kind", "modle"]) == 2
    assert "did you mean model" in capsys.readouterr().err


def test_show_model_pca(capsys):
    assert main(["show", "model", "pca"]) == 0
    out = capsys.readouterr().out
    assert "n_components" in out and "parameters:" in out


def test_show_unknown(capsys):
    assert main(["show", "model", "pcaa"]) == 2
    err = capsys.readouterr().err
    assert "did you mean pca" in err and "Traceback" not in err


@pytest.mark.parametrize("override,match", [
    ("models.pca.n_componets=3", "models.pca.n_componets: unknown parameter of pca; did you mean n_components?"),
    ("models.pca.name=pcb", "models.pca.name: unknown model 'pcb'"),
    ("train.epochs=many", "train.epochs: expected an integer"),
])
def test_bad_recipe_exits_nonzero_and_writes_no_run_dir(tmp_path, capsys, override, match):
    runs = tmp_path / "runs"
    rc = main(["run", str(REPO / "recipes/smoke/reconstruct.yaml"), override, "--runs-dir", str(runs), "--quiet"])
    assert rc == 2
    assert match in capsys.readouterr().err
    assert not runs.exists() or not any(runs.iterdir())


def test_debug_shows_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fwk", "--debug", "show", "model", "nope"], capture_output=True, text=True)
    assert r.returncode != 0 and "Traceback" in r.stderr
    r = subprocess.run([sys.executable, "-m", "fwk", "show", "model", "nope"], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.count("\n") == 1


def test_example_plugin_listed(capsys):
    pytest.importorskip("fwk_example_plugin", reason="examples/fwk-example-plugin is not installed (CI installs it)")
    from fwk.plugins import get_registry

    get_registry(refresh=True)
    assert main(["list", "--kind", "metric"]) == 0
    out = capsys.readouterr().out
    assert "chamfer" in out and "example" in out


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for command in ("list", "show", "run", "eval", "report", "sample", "apply"):
        assert command in out


def test_a_subcommand_that_fails_to_import_fails_fwk():
    # None in sys.modules makes `import fwk.generate` raise ImportError, as a broken module would
    code = "import sys; sys.modules['fwk.generate'] = None; import fwk.cli"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode != 0 and "ModuleNotFoundError: import of fwk.generate halted" in r.stderr


def test_a_reader_that_goes_away_is_not_an_error():
    """`fwk list | head`: no traceback when the pipe closes before fwk has written everything."""
    p = subprocess.Popen([sys.executable, "-m", "fwk", "list"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # before fwk writes its first line
    err = p.stderr.read().decode()
    assert p.wait() == 1
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def test_show_conv_lists_only_recipe_keys(capsys):
    """A conv's build_args (in_channels ... and a strided conv's mode, residual_rate, activation)
    are supplied by the model: `fwk show` names them apart, not as parameters."""
    assert main(["show", "conv", "vcconv"]) == 0
    out = capsys.readouterr().out
    params = out.split("parameters:")[1].split("supplied by the model")[0]
    assert "weight_num" in params and "radius" in params
    for supplied in ("in_channels", "hierarchy", "mode", "residual_rate", "activation"):
        assert supplied not in params, supplied
    assert "supplied by the model that builds it (not recipe keys): in_channels, out_channels, hierarchy, level, " \
           "mode, residual_rate, activation" in out


def test_a_model_supplied_conv_argument_is_refused_in_a_recipe(tmp_path, capsys):
    r = tmp_path / "r.yaml"
    r.write_text("task: reconstruct\ndataset: {name: synthetic-heads, n_subjects: 6, n_vertices: 600}\n"
                 "models: {ae: {name: vae, conv: {name: vcconv, activation: relu}, fully_convolutional: true}}\n")
    assert main(["--quiet", "run", str(r), "--runs-dir", str(tmp_path / "runs")]) == 2
    assert "models.ae.conv.activation: supplied by the model that builds vcconv, not a recipe parameter" \
        in capsys.readouterr().err


def test_device_cuda_without_cuda_is_one_line_and_no_run(tmp_path, capsys, monkeypatch):
    """--device cuda where torch sees no CUDA device is refused before any work (Lightning's auto
    accelerator would train on the CPU without a word): exit 2, one line, no run directory."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    runs = tmp_path / "runs"
    assert main(["run", str(REPO / "recipes" / "smoke" / "reconstruct.yaml"), "--device", "cuda",
                 "--runs-dir", str(runs)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--device cuda: torch" in err and "sees no CUDA device here" in err
    assert not runs.exists() or not any(runs.iterdir())
