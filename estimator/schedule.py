"""When each camera-marker pair's factor is rebuilt: new pairs at once, young ones often, settled
ones at most their fair share per update and only if the rebuilt factor would differ. A part of
``Estimator`` (``estimator.graph``), apart because the schedule is what keeps a large cell's
updates flat, and reads on its own.
"""

from __future__ import annotations

import math

from estimator.init import CameraKey
from estimator.pairs import YOUNG_PAIR, Pair, factors_current

MAX_MATURE_PER_UPDATE = 24  # settled pair factors rebuilt per update at most (see Estimator._due_pairs)


class PairSchedule:
    """The refresh schedule of the pair factors; mixed into ``Estimator``, whose pairs it orders."""

    def _young_again(self, key: tuple[CameraKey, int], pair: Pair) -> None:
        """Schedule a pair with fewer than YOUNG_PAIR observations (new or restarted) as young."""
        if key not in self._young:
            self._settled.pop(key, None)
            self._young[key] = pair

    def _due_pairs(self, now_ns: int) -> list[tuple[tuple[CameraKey, int], Pair]]:
        """Pairs whose factor should be (re)built now.

        New pairs always; young ones (fewer than ``YOUNG_PAIR`` observations) every refresh_s / 10
        so a new segment converges within a fraction of a second; settled ones once per refresh_s,
        the longest unlooked-at first and at most their fair share per update, so refreshes spread
        over the updates instead of all landing in one (that was the p99 latency), and only if the
        rebuilt factor would differ (``Pair.factor_is_current``). Costs the young pairs plus the
        few settled ones looked at, not a pass over every pair (at 2,000 pairs that pass was most
        of an update).
        """
        refresh_ns = int(self.config.refresh_s * 1e9)
        urgent = []
        for key, pair in list(self._young.items()):
            if pair.slot is not None and pair.n >= YOUNG_PAIR:
                del self._young[key]  # settled: its last refresh counts as a look
                self._settled[key] = pair
            elif pair.dirty and (pair.slot is None or now_ns - pair.refreshed_ns >= refresh_ns // 10):
                urgent.append((key, pair))
        # A large cell does not rebuild its share of every pair each update: each rebuilt factor costs
        # iSAM2 a re-elimination, and settled pairs change slowly. Past MAX_MATURE_PER_UPDATE they are
        # looked at less often than refresh_s (64 cameras x 32 markers: every ~4 s).
        share = min(
            max(4, math.ceil(len(self.pairs) / max(self.config.refresh_s * self.config.update_hz, 1.0))),
            MAX_MATURE_PER_UPDATE,
        )
        # At most 2 x share looked at per update (a look costs a Mahalanobis test): the rest wait
        # at the front, so looks spread over the updates too. A pair with nothing new since its
        # last refresh counts as looked at.
        looked, idle = [], []
        for key, pair in self._settled.items():
            if now_ns - pair.refreshed_ns < refresh_ns or len(looked) == 2 * share:
                break
            (looked if pair.dirty else idle).append((key, pair))
        current = factors_current(
            [p for _, p in looked], self.config.max_fused, self.config.refresh_sigma, self.rotation_floor_rad
        )
        mature: list[tuple[tuple[CameraKey, int], Pair]] = []
        for (key, pair), ok in zip(looked, current):
            if ok:
                idle.append((key, pair))
            elif len(mature) < share:
                mature.append((key, pair))  # moves to the back when rebuilt (update)
        for key, pair in idle:
            pair.refreshed_ns = now_ns
            self._settled.move_to_end(key)
        return urgent + mature
