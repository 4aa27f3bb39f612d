"""One rule for seeds, checked before anything is written.

A seed is an integer in ``[0, TRAINING_SEED_LIMIT)``: numpy's ``SeedSequence`` takes no negative
entropy, and test instances are drawn from ``TEST_SEED_BASE + seed`` (:mod:`sdp_cli.algorithm.rollout`), so
every training seed must stay below ``TEST_SEED_BASE`` for the test set to stay disjoint. A loop
collects iteration ``k`` with seed ``1000 * seed + k`` (:class:`sdp_cli.algorithm.loop.LoopConfig`), so a loop
seed must be below ``TRAINING_SEED_LIMIT // LOOP_SEED_STRIDE``.
"""

from __future__ import annotations

from sdp_cli.errors import SdpError

#: test instances come from ``TEST_SEED_BASE + seed``; training seeds stay below it
TEST_SEED_BASE = 1_000_000
TRAINING_SEED_LIMIT = TEST_SEED_BASE
#: a loop's iteration ``k`` collects with seed ``LOOP_SEED_STRIDE * seed + k``
LOOP_SEED_STRIDE = 1000


def check_seed(seed, name: str = "seed", limit: int = TRAINING_SEED_LIMIT) -> int:
    """``seed`` as an int if it is an integer in ``[0, limit)``; else one-line ``SdpError``."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise SdpError(f"{name} must be an integer in [0, {limit - 1}], got {seed!r}")
    if not 0 <= seed < limit:
        raise SdpError(f"{name} must be an integer in [0, {limit - 1}], got {seed}")
    return int(seed)


def check_loop_seed(seed, name: str = "seed", n_algo: int = 1) -> int:
    """A loop seed: its collection seeds ``1000 * seed + k`` (k < n_algo) stay training seeds."""
    seed = check_seed(seed, name, TRAINING_SEED_LIMIT // LOOP_SEED_STRIDE)
    if n_algo > LOOP_SEED_STRIDE:
        raise SdpError(f"n_algo must be <= {LOOP_SEED_STRIDE} (collection seeds are {LOOP_SEED_STRIDE} * seed + k), "
                       f"got {n_algo}")
    return seed


def check_loop_options(given: dict) -> None:
    """``sdp loop``'s training options: its seed also seeds collection (``1000 * seed + k`` must stay seeds)."""
    check_loop_seed(given.get("seed", 0))
