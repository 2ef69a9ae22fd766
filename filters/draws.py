"""Where a filter's random numbers come from: one stream in order of use, or numbers keyed by
what they are for.

A filter asks ``draws.generator(role)`` for the generator of one purpose (the DAS uniforms of a
scan, the pose draw, a resampling offset) and draws from it at once. Two sources implement that:

:class:`OrderedDraws`
    one :class:`numpy.random.Generator` for every role: each draw takes the next numbers of the
    stream, so what a filter draws at an iteration depends on everything it drew before. The
    systems' fixed-schedule runs (BB Table 1, CM) and the ``-v0`` env ids use it.

:class:`SynchronisedDraws`
    common random numbers for comparisons: the numbers of a role at an iteration depend only on
    the key (the world, the draw index), the iteration and the role, never on what was drawn
    before. Two policies that decided differently at some decision still draw the same numbers
    for the same purpose at every later iteration, so their episodes differ by their decisions,
    not by the filter's noise falling differently (synchronised streams: Law, *Simulation
    Modeling and Analysis*, 5th ed., section 11.2). A counter-based generator makes this cheap:
    Philox (Salmon, Moraes, Dror, Shaw, "Parallel random numbers: as easy as 1, 2, 3", SC 2011)
    is a keyed bijection of a 256-bit counter, so every (iteration, role) owns the block of
    counters whose two high words are (role, iteration) and positioning there costs one state
    assignment (~3 us), not a new seeding.

The iteration is set by whoever steps the filter (:class:`slam_gym.episode.Episode`) before each
filter iteration; :meth:`SynchronisedDraws.rekey` starts another future from the current
iteration on (a lookahead's imagined futures).
"""

from __future__ import annotations

import numpy as np

from filters.validation import require

ROLES = (
    "association",          # DAS: one uniform per observation and particle (FS2)
    "scan_pose",            # the pose draw from the scan-refined proposal (FS2)
    "pending_pose",         # the pose draw of an iteration that ended without a scan
    "resample_after_pending",
    "resample_after_heading",
    "resample_after_scan",  # the systematic resampling offset, one per call site
)
"""The purposes a filter draws random numbers for; a role's index is its counter word."""

_ROLE_INDEX = {role: i for i, role in enumerate(ROLES)}

KEY_DOMAIN = 0x5EED_F117
"""Mixed into every key, so a key never equals a generator seeded by the same integers
elsewhere (the world's measurement noise is seeded by the world seed)."""


class OrderedDraws:
    """Every role draws from the one generator ``rng``, in the order the filter uses it."""

    def __init__(self, rng: np.random.Generator):
        require(isinstance(rng, np.random.Generator), "rng", rng, "a numpy.random.Generator")
        self.rng = rng
        self.iteration = 0

    def generator(self, role: str) -> np.random.Generator:
        return self.rng


class SynchronisedDraws:
    """Random numbers keyed by ``(key, iteration, role)`` (module docstring).

    ``key``: non-negative integers naming the stream, e.g. ``(world_seed, draw)``.
    :meth:`generator` returns the one generator of this object positioned at the first number of
    ``role`` at :attr:`iteration`: draw from it before asking for another role.
    """

    def __init__(self, key):
        entropy = [int(k) for k in key]
        require(bool(entropy) and all(k >= 0 for k in entropy), "key", key,
                "a non-empty sequence of non-negative integers")
        self.key = tuple(entropy)
        self.iteration = 0
        self._bits = np.random.Philox(key=self._philox_key(self.key))
        self._generator = np.random.Generator(self._bits)
        self._counter = np.zeros(4, dtype=np.uint64)
        self._state = self._bits.state
        self._state["state"]["counter"] = self._counter

    @staticmethod
    def _philox_key(key: tuple[int, ...]) -> np.ndarray:
        return np.random.SeedSequence([*key, KEY_DOMAIN]).generate_state(2, dtype=np.uint64)

    def generator(self, role: str) -> np.random.Generator:
        index = _ROLE_INDEX.get(role)
        iteration = self.iteration
        if index is None or not iteration >= 0:  # one test on the hot path, named if it fails
            require(index is not None, "role", role, f"one of {ROLES}")
            require(False, "iteration", iteration, "an integer >= 0")
        counter = self._counter
        counter[2] = index
        counter[3] = iteration  # words 0 and 1 stay zero
        state = self._state
        state["buffer_pos"] = 4  # the buffer is empty: the next number comes from the counter
        state["has_uint32"] = 0
        self._bits.state = state  # the dict holds the counter array: one assignment positions
        return self._generator

    def position(self, role: str) -> tuple[int, ...]:
        """Where ``role``'s numbers at :attr:`iteration` start: the Philox key and counter words
        (what a test compares to show two runs draw the same numbers for the same purpose)."""
        state = self.generator(role).bit_generator.state["state"]
        return (*(int(k) for k in state["key"]), *(int(c) for c in state["counter"]))

    def rekey(self, extra: int) -> None:
        """From :attr:`iteration` on, draw from the stream keyed by this key extended with
        ``extra`` and the current iteration: another future of the same past."""
        require(int(extra) >= 0, "extra", extra, "a non-negative integer")
        self.key = (*self.key, int(extra), int(self.iteration))
        self._bits = np.random.Philox(key=self._philox_key(self.key))
        self._generator = np.random.Generator(self._bits)
        self._state = self._bits.state
        self._state["state"]["counter"] = self._counter


def as_draws(rng) -> OrderedDraws | SynchronisedDraws:
    """``rng`` as a source of draws: a Generator is one ordered stream; a source is itself."""
    if isinstance(rng, (OrderedDraws, SynchronisedDraws)):
        return rng
    require(isinstance(rng, np.random.Generator), "rng", rng,
            "a numpy.random.Generator, an OrderedDraws or a SynchronisedDraws")
    return OrderedDraws(rng)
