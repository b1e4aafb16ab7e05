"""tacf.argument_types: the argparse types every `tacf` command shares, and that the commands use them (a NaN rate
passed `tacf bench service`'s `<= 0` check and ran)."""
from __future__ import annotations

import argparse

import pytest

from tacf import argument_types as types


@pytest.mark.parametrize("parse, text, value", [
    (types.positive_number, "2.5", 2.5), (types.positive_number, "1e-3", 1e-3),
    (types.seconds, "0", 0.0), (types.seconds, "1.5", 1.5),
    (types.integer(1), "3", 3), (types.integer(), "-7", -7), (types.integer(0, 2), "2", 2),
    (types.port, "0", 0), (types.port, "65535", 65535), (types.quality, "1", 1),
    (types.positive_up_to(1440), "1440", 1440.0), (types.positive_up_to(1440), "0.5", 0.5),
    (types.box, "1,2,3,4", (1.0, 2.0, 3.0, 4.0)), (types.box, " 1 2, 3.5 4 ", (1.0, 2.0, 3.5, 4.0)),
    (types.box, "-5,-5,1,1", (-5.0, -5.0, 1.0, 1.0)),
])
def test_good_values_are_taken(parse, text, value):
    assert parse(text) == value


@pytest.mark.parametrize("parse, text, expected", [
    (types.positive_number, "nan", "expected a finite number > 0"),
    (types.positive_number, "inf", "expected a finite number > 0"),
    (types.positive_number, "-Infinity", "expected a finite number > 0"),
    (types.positive_number, "0", "expected a finite number > 0"),
    (types.positive_number, "-1", "expected a finite number > 0"),
    (types.positive_number, "fast", "expected a finite number > 0"),
    (types.seconds, "nan", "expected a finite number of seconds >= 0"),
    (types.seconds, "inf", "expected a finite number of seconds >= 0"),
    (types.seconds, "-0.1", "expected a finite number of seconds >= 0"),
    (types.positive_number, "1e300", "expected a finite number > 0 and <= 1e+09"),
    (types.seconds, "1e10", "expected a finite number of seconds >= 0 and <= 1e+09"),
    (types.integer(1), "0", "expected an integer >= 1"),
    (types.integer(1), "2.5", "expected an integer >= 1"),
    (types.integer(maximum=3), "4", "expected an integer <= 3"),
    (types.integer(), "x", "expected an integer"),
    (types.port, "70000", "expected a port number 0-65535"),
    (types.port, "-1", "expected a port number 0-65535"),
    (types.quality, "0", "expected a JPEG quality 1-100"),
    (types.quality, "101", "expected a JPEG quality 1-100"),
    (types.positive_up_to(1440), "1e307", "expected a number > 0 and <= 1440"),
    (types.positive_up_to(1440), "0", "expected a number > 0 and <= 1440"),
    (types.positive_up_to(1440), "nan", "expected a number > 0 and <= 1440"),
    (types.box, "1,2,3", "expected x,y,w,h: four finite numbers with w and h > 0"),
    (types.box, "1,2,3,0", "expected x,y,w,h"),
    (types.box, "1,2,-3,4", "expected x,y,w,h"),
    (types.box, "nan,2,3,4", "expected x,y,w,h"),
    (types.box, "1,2,inf,4", "expected x,y,w,h"),
    (types.box, "a,b,c,d", "expected x,y,w,h"),
])
def test_bad_values_are_refused_with_the_value_and_what_was_expected(parse, text, expected):
    with pytest.raises(argparse.ArgumentTypeError) as refused:
        parse(text)
    assert str(refused.value).startswith(f"{text!r}: {expected}"), str(refused.value)


@pytest.mark.parametrize("argv", [
    ["bench", "service", "--fps", "nan"], ["bench", "service", "--seconds", "inf"],
    ["bench", "service", "--warmup", "-1"], ["bench", "service", "--feeds", "0"],
    ["demo", "--seconds", "nan"], ["demo", "--box", "1,2,nan,4"], ["demo", "--every", "0"],
    ["publish", "scene", "--key", "cam/a", "--wait-subscriber", "nan"],
    ["publish", "scene", "--key", "cam/a", "--frames", "-1"],
    ["publish", "scene", "--key", "cam/a", "--quality", "0"],
    ["start", "--key", "cam/a", "--box", "1,2,0,4"], ["reinit", "abc", "--box", "1,2,3"],
    ["start", "--key", "cam/a", "--box", "1,2,3,4", "--connect", "tcp/127.0.0.1:1", "--seq", "-1"],
    ["reinit", "abc", "--box", "1,2,3,4", "--connect", "tcp/127.0.0.1:1", "--seq", "-1"],
    ["mavlink", "--key", "cam/a", "--link", "udpin:127.0.0.1:99999", "--system", "0"],
    ["mavlink", "--key", "cam/a", "--link", "udpin:127.0.0.1:99999", "--component", "256"],
    ["dashboard", "--history", "nan"], ["dashboard", "--history", "1e307"], ["foxglove", "--image-hz", "0"],
    ["serve", "--init-wait", "nan"], ["serve", "--max-sessions", "0"],
    ["track", "clip.mp4", "--box", "1,2,3,inf"], ["eval", "root", "--workers", "0"],
    ["eval", "root", "--max-frames", "0"], ["eval", "root", "--shifts", "-1"],
    ["bench", "tracker", "--max-frames", "-5"],
    # finite but past what a wait takes: an OverflowError, Zenoh's "negative timeout"
    ["nodes", "--follow", "--duration", "1e10"], ["list", "--timeout", "1e20"],
])
def test_every_command_refuses_a_meaningless_number_as_a_usage_error(argv, capsys):
    from tacf.cli import main

    with pytest.raises(SystemExit) as refused:
        main(argv)
    err = capsys.readouterr().err
    assert refused.value.code == 2 and f"error: argument {argv[-2]}" in err and "Traceback" not in err, err


@pytest.mark.parametrize("argv", [["publish", "", "--key", "cam/a"], ["demo", ""], ["track", "", "--box", "1,2,3,4"]])
def test_an_empty_source_is_a_usage_error(argv, capsys):
    """An empty SOURCE ("$VIDEO" with the variable unset) was the current folder, read as a folder of images."""
    from tacf.cli import main

    with pytest.raises(SystemExit) as refused:
        main(argv)
    err = capsys.readouterr().err
    assert refused.value.code == 2 and "error: argument SOURCE: '': expected a source" in err, err


@pytest.mark.parametrize("command", ["serve", "list", "watch", "publish scene --key cam/a"])
def test_an_empty_zenoh_config_is_a_usage_error(command, capsys):
    """`--zenoh-config "$ZENOH_CONFIG"` with the variable unset: the service took it for no file (Zenoh's defaults,
    without a word), the clients for the current folder ("bad Zenoh configuration (.): Is a directory")."""
    from tacf.cli import main

    with pytest.raises(SystemExit) as refused:
        main([*command.split(), "--zenoh-config", ""])
    err = capsys.readouterr().err
    assert refused.value.code == 2 and "argument --zenoh-config: '': expected a Zenoh JSON5 config file" in err, err


def test_an_empty_zenoh_config_file_is_refused_from_python_too():
    """`ZenohOptions(config_file=os.environ.get("ZENOH_CONFIG", ""))` with the variable unset: the service took it
    for no file, a client for no file and none of its loopback defaults (listening on every interface)."""
    from tacf.zenoh_options import ZenohOptions

    with pytest.raises(ValueError, match="config_file is empty: give a Zenoh JSON5 file, or None for the defaults"):
        ZenohOptions(config_file="")
    assert ZenohOptions(config_file=None).config_file is None
