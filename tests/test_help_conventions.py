"""Commands that write angles state their sign convention (docs/model.md#hardware-conventions)."""
from __future__ import annotations

import pytest
from click.testing import CliRunner

from psdcal.cli import _register, cli


@pytest.mark.parametrize("command", ["locate", "aoa"])
def test_angle_sign_in_help(command):
    _register()
    out = " ".join(CliRunner().invoke(cli, [command, "--help"]).output.split())
    assert "alpha_x > 0" in out and "alpha_y > 0" in out
    assert "docs/model.md#hardware-conventions" in out
