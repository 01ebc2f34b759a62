"""The suite's one wait setting, AOI3D_TEST_TIMEOUT_SCALE: unset or empty is 1, a bad value
is one clear error naming the variable."""

import pytest

from tests.support.timeouts import timeout_scale


def test_the_timeout_scale_reads_one_variable() -> None:
    assert timeout_scale({}) == 1.0
    assert timeout_scale({"AOI3D_TEST_TIMEOUT_SCALE": ""}) == 1.0  # (an empty value broke
    assert timeout_scale({"AOI3D_TEST_TIMEOUT_SCALE": " 3 "}) == 3.0  # collection of 38 files)
    for bad in ("x", "0", "-2", "nan", "inf"):
        with pytest.raises(ValueError, match="AOI3D_TEST_TIMEOUT_SCALE"):
            timeout_scale({"AOI3D_TEST_TIMEOUT_SCALE": bad})
