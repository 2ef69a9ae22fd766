"""scripts/performance/episode_bits.py: the digest that keeps the episodes' reference small."""

import numpy as np
from script_loader import load_script

bits = load_script("performance/episode_bits.py")


def record(x: float = 0.25):
    obs = np.array([1.0, x, np.nan])
    return [obs, {"b": 2, "a": np.int64(3)}, (obs, -1.5, False, True, {"k": None, "s": "x"})]


def test_equal_records_give_equal_digests_whatever_the_dict_order():
    a = record()
    b = record()
    b[1] = {"a": np.int64(3), "b": 2}
    assert bits.digest(a) == bits.digest(b)


def test_one_ulp_one_flag_or_one_dtype_changes_the_digest():
    base = bits.digest(record())
    assert bits.digest(record(np.nextafter(0.25, 1.0))) != base
    flipped = record()
    flipped[2] = (flipped[2][0], -1.5, True, True, flipped[2][4])
    assert bits.digest(flipped) != base
    as_float32 = record()
    as_float32[0] = as_float32[0].astype(np.float32)
    assert bits.digest(as_float32) != base
