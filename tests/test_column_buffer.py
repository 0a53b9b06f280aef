"""A matrix grown by columns in place (identification.column_buffer), and the engine's matrices grown with it:
the same values, to the bit, as the copies np.hstack made."""

import numpy as np
import pytest

from identification.column_buffer import ColumnBuffer
from identification.discovery import _projected_scores, _standardized


@pytest.mark.parametrize("order", ["C", "F"])
def test_appended_columns_leave_the_views_handed_out_before_as_they_were(order):
    rng = np.random.default_rng(3)
    M = rng.standard_normal((50, 4))
    buf = ColumnBuffer.holding(M, room=1, order=order)
    first = buf.view()
    np.testing.assert_array_equal(first, M)
    extra = rng.standard_normal((50, 3))
    grown = buf.append(extra[:, :1])  # into the room
    assert np.shares_memory(grown, first)
    grown2 = buf.append(extra[:, 1:])  # past the room: moved to a larger buffer
    np.testing.assert_array_equal(grown2, np.hstack([M, extra]))
    np.testing.assert_array_equal(first, M)
    np.testing.assert_array_equal(grown, np.hstack([M, extra[:, :1]]))
    if order == "F":  # each column contiguous (the replacement screening gathers columns)
        assert grown2.flags.f_contiguous
    again = buf.truncate(4)
    np.testing.assert_array_equal(again, M)
    np.testing.assert_array_equal(buf.append(extra[:, 2:]), np.hstack([M, extra[:, 2:]]))
    with pytest.raises(ValueError, match="cannot truncate 5 columns to 6"):
        buf.truncate(6)


def test_the_engines_reductions_on_a_grown_matrix_are_those_of_its_copy():
    # the screening's scores (a matrix-vector product over the standardized columns), the standardizing
    # itself and its NaN columns: the same bits on a view of a buffer with room as on np.hstack's copy
    rng = np.random.default_rng(11)
    F = rng.standard_normal((3000, 40)) * rng.lognormal(0, 3, 40)
    F[:, 7] = 2.5  # constant: unusable, all NaN
    law = rng.standard_normal((3000, 1)) ** 2
    buf = ColumnBuffer(3000, 40, room=2)
    Z = _standardized(F, out=buf.view())
    np.testing.assert_array_equal(Z, _standardized(F))
    assert np.isnan(Z[:, 7]).all()
    grown = buf.append(_standardized(law))
    copied = np.hstack([_standardized(F), _standardized(law)])
    np.testing.assert_array_equal(grown, copied)
    r = rng.standard_normal(3000)
    model = F[:, [0, 3]]
    np.testing.assert_array_equal(_projected_scores(grown, r, model), _projected_scores(copied, r, model))
