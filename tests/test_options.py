"""options.py: a job's flags, --config FILE and checks come from its options dataclass."""

import argparse
from dataclasses import dataclass

import pytest

from evdnerf_ros.cli import main
from evdnerf_ros.errors import InputError
from evdnerf_ros.options import add_options, load_config, options_from_args, option


@dataclass(frozen=True)
class Knobs:
    views: int | None = option(None, "training views", kind=int, low=1, high=100, none_help="all")
    c_pos: float = option(0.2, "C+", low=0.01, high=10.0)
    step_ns: int = option(1_000_000, "finest step", flag="--step", duration=True, low=1_000, high=10**12)
    method: str = option("auto", "method", choices=("auto", "rate"))
    refine: bool = option(True, "skip the refinement")
    size: tuple | None = option(None, "image size", kind=int, nargs=2, metavar=("W", "H"), low=1, high=4096)
    tuning: float = option(8.0, "config-only knob", low=0, high=100, cli=False)


def parse(argv):
    p = argparse.ArgumentParser()
    add_options(p, Knobs)
    return options_from_args(Knobs, p.parse_args(argv))


def test_defaults_come_from_the_dataclass():
    assert parse([]) == Knobs()


def test_flags_are_typed_and_checked():
    k = parse(["--views", "4", "--c-pos", "0.3", "--step", "10ms", "--method", "rate", "--no-refine",
               "--size", "64", "48"])
    assert k == Knobs(views=4, c_pos=0.3, step_ns=10_000_000, method="rate", refine=False, size=(64, 48))
    for bad in (["--views", "0"], ["--c-pos", "nan"], ["--step", "1ns"], ["--method", "best"],
                ["--views", "2.5"]):
        with pytest.raises(SystemExit):
            parse(bad)
    with pytest.raises(InputError, match=r"--size H: .*4096"):
        parse(["--size", "64", "5000"])


def test_help_shows_range_and_default(capsys):
    with pytest.raises(SystemExit):
        parse(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "C+ (in [0.01, 10], default 0.2)" in out
    assert "finest step (in [1us, 1000s], default 1ms)" in out
    assert "training views (in [1, 100], default all)" in out and "--no-refine" in out
    assert "--tuning" not in out


def test_config_file_then_flags(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("views: 6\nstep: 2ms\nc_pos: 0.25\ntuning: 3\nsize: [32, 24]\n")
    k = parse(["--config", str(cfg), "--views", "8"])
    assert k == Knobs(views=8, c_pos=0.25, step_ns=2_000_000, tuning=3.0, size=(32, 24))
    assert load_config(cfg, Knobs)["step_ns"] == 2_000_000


@pytest.mark.parametrize("text, needle", [
    ("viewz: 3\n", "viewz: unknown option; allowed:"),
    ("views: 0\n", "views: must be"),
    ("method: best\n", "method: 'best' is not one of auto, rate"),
    ("refine: 1\n", "refine: expected true or false"),
    ("size: [32]\n", "size: expected 2 values"),
    ("- a list\n", "expected a mapping of option: value"),
    ("views: [\n", "not valid YAML"),
])
def test_bad_config_names_file_and_key(tmp_path, text, needle):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    with pytest.raises(InputError) as ei:
        parse(["--config", str(cfg)])
    assert str(ei.value).startswith(str(cfg)) and needle in str(ei.value), str(ei.value)


def test_a_job_takes_its_config_file(tmp_path, capsys):
    """`evdnerf sync --config`: a config value reaches the job, and a bad one is one line."""
    cfg = tmp_path / "sync.yaml"
    cfg.write_text("method: best\n")
    assert main(["sync", str(tmp_path), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sync.yaml: method: 'best' is not one of" in err
