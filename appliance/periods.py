"""Wall-clock aligned measurement periods: which period a time falls in, which periods completed."""

from __future__ import annotations

import math

PERIOD_TOLERANCE_S = 1.0  # a start/stop within this of a boundary still counts as a full period


def period_start(wall: float, period_s: float) -> float:
    """Start of the wall-clock aligned period holding ``wall``."""
    return math.floor(wall / period_s) * period_s


class PeriodClock:
    """Tracks the current period; ``advance`` returns the starts of the periods completed."""

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self.current: float | None = None
        self.first_wall: float | None = None

    def advance(self, wall: float) -> list[float]:
        if self.current is None:
            self.current = period_start(wall, self.period_s)
            self.first_wall = wall
            return []
        done: list[float] = []
        while wall >= self.current + self.period_s:
            done.append(self.current)
            self.current += self.period_s
        return done

    def state(self) -> dict:
        return {"period_s": self.period_s, "current": self.current, "first_wall": self.first_wall}

    def restore(self, state: dict) -> None:
        if float(state["period_s"]) != self.period_s:
            raise ValueError(
                f"saved period length {state['period_s']} s differs from measures.period_s = {self.period_s}"
            )
        self.current = state["current"]
        self.first_wall = state["first_wall"]
