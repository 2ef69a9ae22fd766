"""filters.draws: random numbers keyed by purpose and time (common random numbers)."""

import copy

import numpy as np
import pytest

from filters.draws import ROLES, OrderedDraws, SynchronisedDraws, as_draws


def test_a_roles_numbers_at_an_iteration_do_not_depend_on_what_was_drawn_before():
    draws = SynchronisedDraws((7, 0))
    draws.iteration = 5
    first = draws.generator("association").random(12)
    draws.iteration = 3
    draws.generator("scan_pose").standard_normal((4, 3))
    draws.generator("association").random(1000)
    draws.iteration = 5
    again = draws.generator("association").random(12)
    np.testing.assert_array_equal(first, again)
    fresh = SynchronisedDraws((7, 0))
    fresh.iteration = 5
    np.testing.assert_array_equal(fresh.generator("association").random(12), first)


def test_roles_iterations_and_keys_draw_different_numbers():
    draws = SynchronisedDraws((7, 0))
    samples = {}
    for key in ((7, 0), (7, 1), (8, 0)):
        source = SynchronisedDraws(key)
        for iteration in (0, 1):
            source.iteration = iteration
            for role in ROLES:
                samples[(key, iteration, role)] = tuple(source.generator(role).random(4))
    assert len(set(samples.values())) == len(samples)
    draws.iteration = 2
    u = draws.generator("resample_after_scan").random(200_000)
    assert abs(u.mean() - 0.5) < 0.005 and 0.0 <= u.min() and u.max() < 1.0


def test_position_names_key_and_counter_and_rekey_starts_another_future():
    draws = SynchronisedDraws((3, 1))
    draws.iteration = 9
    before = draws.position("scan_pose")
    assert before[2:] == (0, 0, ROLES.index("scan_pose"), 9)
    past = SynchronisedDraws((3, 1))
    past.iteration = 4
    old = past.generator("association").random(3)
    draws.rekey(11)
    assert draws.position("scan_pose")[:2] != before[:2]
    draws.iteration = 4  # the rekeyed stream is another stream at every iteration
    assert not np.array_equal(draws.generator("association").random(3), old)


def test_a_copy_draws_what_the_original_draws():
    draws = SynchronisedDraws((1, 2))
    draws.iteration = 6
    twin = copy.deepcopy(draws)
    np.testing.assert_array_equal(twin.generator("scan_pose").standard_normal(5),
                                  draws.generator("scan_pose").standard_normal(5))


def test_ordered_draws_are_one_stream_in_order_of_use():
    rng = np.random.default_rng(4)
    ordered = as_draws(rng)
    assert isinstance(ordered, OrderedDraws)
    a = ordered.generator("association").random(3)
    b = ordered.generator("scan_pose").random(3)
    np.testing.assert_array_equal(np.concatenate([a, b]), np.random.default_rng(4).random(6))
    assert as_draws(ordered) is ordered


@pytest.mark.parametrize("make, field", [
    (lambda: SynchronisedDraws((1,)).generator("pose"), "role"),
    (lambda: SynchronisedDraws(()), "key"),
    (lambda: SynchronisedDraws((-1, 0)), "key"),
    (lambda: as_draws(3), "rng"),
    (lambda: SynchronisedDraws((1,)).rekey(-2), "extra"),
])
def test_bad_input_names_the_field(make, field):
    with pytest.raises(ValueError, match=f"^{field}="):
        make()
