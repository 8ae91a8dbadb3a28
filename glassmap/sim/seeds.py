"""Fixed seed ranges of generated worlds: test worlds are never used for training or tuning.

``test`` seeds are what ``glassmap eval`` (the generalisation benchmark) measures on; ``validation`` and
``training`` are disjoint ranges for model selection and training. Code that trains or tunes on generated
worlds calls :func:`check_not_test` first.
"""

from __future__ import annotations

from collections.abc import Iterable

TEST_SEEDS = range(0, 100)
VALIDATION_SEEDS = range(1000, 2000)
TRAINING_SEEDS = range(10_000, 100_000)

SPLITS = {"test": TEST_SEEDS, "validation": VALIDATION_SEEDS, "training": TRAINING_SEEDS}


class TestSeedError(ValueError):
    """A test-world seed was given to code that trains or tunes."""

    __test__ = False  # not a pytest test class


def split_of(seed: int) -> str:
    """``test``, ``validation``, ``training`` or ``unassigned`` (outside every fixed range)."""
    for name, r in SPLITS.items():
        if seed in r:
            return name
    return "unassigned"


def check_not_test(seeds: Iterable[int], purpose: str = "training") -> list[int]:
    """Return ``seeds`` as a list; raise TestSeedError if any is a test seed (0-99)."""
    out = [int(s) for s in seeds]
    bad = [s for s in out if s in TEST_SEEDS]
    if bad:
        raise TestSeedError(f"seeds {bad[:5]}{' ...' if len(bad) > 5 else ''} are test-world seeds "
                            f"({TEST_SEEDS.start}-{TEST_SEEDS.stop - 1}) and must not be used for {purpose}; "
                            f"use validation seeds {VALIDATION_SEEDS.start}-{VALIDATION_SEEDS.stop - 1} or "
                            f"training seeds {TRAINING_SEEDS.start}-{TRAINING_SEEDS.stop - 1}")
    return out
