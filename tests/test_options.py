"""The camera options (svelive.options): each defined once; the command line, a settings table and the
service's settings give the same source options and cameras."""

from __future__ import annotations

import argparse

import pytest

from svelive import SveliveError
from svelive.options import CAMERA_OPTIONS, CameraSettings, add_camera_option, build_camera


def test_every_verb_takes_the_camera_options_from_one_table():
    from svelive.cli import build_parser

    parser = build_parser()
    verbs = {name: p for action in parser._subparsers._group_actions for name, p in action.choices.items()}
    nested = verbs["calibrate"]._subparsers._group_actions[0].choices
    seen = 0
    for p in [*verbs.values(), *nested.values()]:
        for action in p._actions:
            for name, (flag, kind) in CAMERA_OPTIONS.items():
                if flag in action.option_strings:
                    seen += 1
                    assert action.dest == name and (action.type or str) is kind
    assert seen >= 15  # --pattern 7 times, --cfa and --black-level 4 times each, more of --bits and --white-level


def test_args_table_and_service_settings_agree():
    from service.pipeline import PipelineConfig

    p = argparse.ArgumentParser()
    for name in CAMERA_OPTIONS:
        add_camera_option(p, name)
    args = p.parse_args(["--pattern", "dual-iso", "--black-level", "64", "--white-level", "4000"])
    given = CameraSettings.from_args(args)
    assert given == CameraSettings.from_mapping({"pattern": "dual-iso", "black_level": 64.0, "white_level": 4000.0,
                                                 "method": "weighted"})
    config = PipelineConfig(pattern="dual-iso", black_level=64.0, white_level=4000.0)
    assert CameraSettings.from_mapping(config) == given
    assert given.source_options() == {"pattern": "dual-iso", "cfa": None, "bits": None, "black_level": 64.0,
                                      "white_level": 4000.0}
    assert build_camera(given).cfa.name == "RGGB"
    with pytest.raises(SveliveError, match="--cfa none was given"):
        build_camera(CameraSettings("dual-iso", "none"))
    assert build_camera(CameraSettings("1,4/16,64", "mono")).cfa is None
