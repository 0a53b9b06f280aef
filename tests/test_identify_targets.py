"""identify's targets are checked at the edge: an unknown name is a UserError before any fitting, not a model
with nothing in it, and a comma-separated string is the CLI's list."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.errors import UserError
from identification.effects_physics import flight_rows
from identification.identify import identify
from identification.table import TARGET_NAMES, Dataset


def _rows(n: int = 600, seed: int = 0) -> Dataset:
    """n rows of the paper vehicle's exact physics at random states (truth targets)."""
    xi, u, y = flight_rows(n, seed)
    return Dataset(t=np.arange(n) * 0.004, xi=xi, u=u, targets=y, source="synthetic", format="rows",
                   target_source="truth")


@pytest.mark.parametrize("bad", [["fx"], ["ax", "wx'"], [], "dwx,dwq"])
def test_an_unknown_or_missing_target_is_a_user_error(bad):
    with pytest.raises(UserError) as err:
        identify(_rows(), engine="sparse", targets=bad, progress=False)
    text = str(err.value)  # the message and its hint
    assert ("unknown target" in text or "no targets" in text) and "ax, ay, az, dwx, dwy, dwz" in text


def test_a_comma_separated_string_names_the_targets():
    model = identify(_rows(), engine="sparse", targets="dwz,dwx", progress=False)
    assert list(model.targets) == ["dwx", "dwz"]
    assert set(model.targets) < set(TARGET_NAMES)
