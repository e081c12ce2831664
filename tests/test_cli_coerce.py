"""Option values converted without pydantic (labelaudit/cli/coerce.py) equal Typer's own conversion."""

from __future__ import annotations

import subprocess
import sys
from enum import Enum
from pathlib import Path

import pytest
import typer
import typer.core
from typer.main import get_command

from labelaudit.cli import app, coerce

PLAIN = typer.core.build_runtime_param
pytestmark = pytest.mark.skipif(
    not getattr(PLAIN, "plain_values", False), reason="this Typer converts without pydantic"
)

SAMPLES = {
    str: ["x", "", " a ", "Car,Van", "ü"],
    bool: [True, False, "true", "0", "yes"],
    int: ["2", "-1", "+3", "0012", "0", " 2 ", "1_0", "2.0", "1.5", "abc", "", "٣", 3, "99999999999999999999"],
    float: ["1", "1.5", "-.5", "1.", "+2e3", "1E-3", "nan", "inf", "-Infinity", "x", " 2 ", "1_0.5", "", "0x1p3", 0.25],
    Path: ["a", "", "/tmp", "~/x", " b ", Path("c")],
}


def _original():
    """Typer's own converter builder, the one :func:`coerce.install` wrapped."""
    import typer._coercion

    return typer._coercion.build_runtime_param


def _params():
    group = get_command(app)
    for name, command in sorted(group.commands.items()):
        for param in command.params:
            if hasattr(param, "type_descriptor"):
                yield name, command, param


def _samples(descriptor) -> list:
    a = descriptor.annotation
    if descriptor.is_list:
        return [("a", "b"), ["c"], (), "d"]
    if isinstance(a, type) and issubclass(a, Enum):
        return [*(c.value for c in a), *(str(c.value).upper() for c in a), "bogus", "", next(iter(a))]
    return SAMPLES.get(a, [])


def _outcome(runtime_param, value, param, ctx):
    try:
        got = runtime_param._coerce_value(value, param=param, ctx=ctx)
    except Exception as exc:
        return ("raised", type(exc).__name__, str(exc))
    return ("value", type(got), got)


def test_plain_values_convert_as_typer_does_on_every_option_of_every_command():
    compared = 0
    for name, command, param in _params():
        ctx = typer.core._click.Context(command, info_name=name)
        desc = param.type_descriptor
        plain, original = PLAIN(desc), _original()(desc)
        for value in _samples(desc):
            a, b = _outcome(plain, value, param, ctx), _outcome(original, value, param, ctx)
            if a[0] == "value" and isinstance(a[2], float) and a[2] != a[2]:  # nan
                assert b[0] == "value" and b[2] != b[2], (name, param.name, value)
            else:
                assert a == b, (name, param.name, value)
            compared += 1
    assert compared > 300  # every command's options were found and exercised


def test_the_plain_converter_covers_infer_so_its_start_up_imports_no_pydantic(tmp_path):
    code = (
        "import sys; from typer.main import get_command; from labelaudit.cli import app; "
        "g = get_command(app); c = g.make_context('labelaudit', ['infer', 'd']); "
        "s = g.get_command(c, 'infer'); "
        "x = s.make_context('infer', ['d', '--workers', '2', '-q', '--overwrite', '--model', '3d', "
        "'--dataset-format', 'kitti', '--limit', '3', '--classes', 'Car', '-o', 'out', '--config', 'm.toml'], parent=c); "
        "print(x.params['workers'], x.params['model'].value, x.params['limit'], x.params['config'], 'pydantic' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["2", "3d", "3", "m.toml", "False"]


def test_a_value_typer_must_word_still_gets_typer_s_message():
    from typer.testing import CliRunner

    runner = CliRunner()
    result = runner.invoke(app, ["infer", "d", "--workers", "abc"])
    assert result.exit_code == 2
    assert "Input should be a valid integer" in result.output  # pydantic's wording, as before
    result = runner.invoke(app, ["infer", "d", "--model", "4d"])
    assert result.exit_code == 2 and "'4d' is not one of 'bev', '3d'" in result.output


def test_install_is_idempotent():
    assert coerce.install() and typer.core.build_runtime_param is PLAIN


def test_another_typer_release_line_is_left_untouched(monkeypatch):
    monkeypatch.setattr(typer, "__version__", "0.30.0")
    assert not coerce.install()
    assert typer.core.build_runtime_param is PLAIN  # what an earlier install did stays; nothing new is wrapped
