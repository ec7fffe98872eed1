"""One set of command-line conventions: common options, help on every option, one output flag,
one detection threshold."""

import argparse

import pytest

from bfpsf.cli import COMMANDS, build_parser, main
from bfpsf.measure.sources import DETECTION_THRESHOLD


def _parsers():
    """(name, parser) of every command and simulate target."""
    found = []

    def walk(parser, name):
        found.append((name, parser))
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    walk(sub, f"{name} {sub_name}".strip())

    walk(build_parser(), "")
    return found[1:]


def test_every_option_has_help_without_development_notes():
    for name, parser in _parsers():
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help, f"bfpsf {name} {action.option_strings or action.dest}"
            assert "issue" not in action.help.lower(), f"bfpsf {name}: {action.help}"


@pytest.mark.parametrize("name", [n for n in COMMANDS if n != "simulate"] + ["simulate flats"])
def test_common_options_everywhere(name):
    parser = dict(_parsers())[name]
    options = {option for action in parser._actions for option in action.option_strings}
    assert {"--progress", "--no-progress", "-v", "-q", "--threads"} <= options
    outputs = options & {"-o", "--output", "--out"}
    assert outputs in (set(), {"-o", "--output"}), name


def test_one_detection_threshold_default():
    parsers = dict(_parsers())
    for name in ("measure", "psf", "photometry"):
        assert parsers[name].get_default("threshold") == DETECTION_THRESHOLD


def test_progress_defaults_to_off_without_a_terminal_and_threads_apply(capsys, monkeypatch):
    from bfpsf.model import tiles

    seen = {}

    def fake_run(args):
        seen["progress"] = args.progress
        seen["workers"] = tiles.default_workers()
        return 0

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setattr(tiles, "_WORKERS", None)
    parser = build_parser()
    args = parser.parse_args(["slope", "x.ecsv", "--threads", "3"])
    args._run = fake_run
    monkeypatch.setattr("bfpsf.cli.build_parser", lambda: _Fixed(args))
    assert main([]) == 0
    assert seen == {"progress": False, "workers": 3}
    args.threads, args.progress = 0, None
    assert main([]) == 1
    assert capsys.readouterr().err == "bfpsf slope: error: --threads must be at least 1, got 0\n"


class _Fixed:
    """A parser that returns fixed arguments."""

    def __init__(self, args):
        self.args = args

    def parse_args(self, argv):
        return self.args
