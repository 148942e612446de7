"""How long bench/peers.py makes each run: OpenSplat's -n and segs's trainer.max_steps for a budget
from the runs before it, and whether a run used its budget (its docstring: the protocol)."""
from __future__ import annotations

import numpy as np

PEER_PHASE_STEPS = 3000  # its --resolution-schedule default: 1/4 size, then 1/2 from 3,000, full from 6,000
PEER_PHASE_SLOWDOWN = 0.4  # rate of a resolution phase not seen yet, relative to the one before
AIM = 0.95  # runs are sized to end at this fraction of the budget (later steps are slower)
PILOT_RATE_FACTOR = 0.8  # the first budget's rates from a pilot alone (small map, fastest steps)
TRIES, FIT_LOW, FIT_HIGH = 3, 0.85, 1.08  # a run ending outside [LOW, HIGH] x budget is sized again (peer_iterations, segs_max_steps)


def peer_phase(step: int) -> int:
    """Resolution phase of an OpenSplat step (0: 1/4 size, 1: 1/2, 2: full)."""
    return min(step // PEER_PHASE_STEPS, 2)


def peer_rates(runs: list[dict]) -> tuple[float, dict[int, float]]:
    """(startup seconds, {phase: steps/s}) from the latest runs: each phase's rate over the last
    half of its steps in the latest run that printed >= 40 of them."""
    startup, rates = runs[-1]["steps"][0][0], {}
    for phase in range(3):
        for r in reversed(runs):
            pts = _phase_points(r["steps"], phase)
            if len(pts) >= 40:
                rates[phase] = _late_rate(pts)
                break
    return startup, rates


def _phase_points(log: list, phase: int) -> list[tuple[float, int]]:
    """The (seconds, step) points of a log [[seconds, step], ...] inside one resolution phase."""
    return [(t, s) for t, s in log if peer_phase(int(s)) == phase]


def _late_rate(pts: list[tuple[float, int]]) -> float:
    """Steps/s over the last half of the points."""
    half = pts[len(pts) // 2 :]
    return (half[-1][1] - half[0][1]) / max(half[-1][0] - half[0][0], 1e-6)


def peer_seconds(n: int, startup: float, rates: dict[int, float]) -> float:
    """Predicted seconds from launch to step n."""
    t, rate = startup, None
    for phase in range(3):
        rate = rates.get(phase, (rate or 1.0) * PEER_PHASE_SLOWDOWN)
        lo, hi = phase * PEER_PHASE_STEPS, (phase + 1) * PEER_PHASE_STEPS if phase < 2 else n
        t += max(min(n, hi) - lo, 0) / rate
    return t


def peer_iterations(budget_s: float, runs: list[dict], rate_factor: float = 1.0) -> int:
    """Iterations for a run of budget_s. Two runs of this budget that ended either side of it: n
    interpolated between them to end at the budget (`bracketed`). Else, for AIM x budget: the
    step the latest run printed at that time when it ran that long, else the largest n whose
    predicted time fits (peer_seconds, binary search) and never fewer than a run that ended
    before that time gives at its final pace (`final_rate`); rate_factor scales the measured
    rates (below 1 after the pilot alone: its first steps are its fastest)."""
    tries = [(int(r["iterations"]), r["points"][-1]["seconds"]) for r in runs if r.get("budget_s") == budget_s]
    n = bracketed(budget_s, tries)
    if n is not None:
        return n
    target = AIM * budget_s
    log = runs[-1]["steps"]
    if log[-1][0] >= target:  # its own clock: steps slow down as it densifies
        return max(next(int(s) for t, s in log if t >= target), 1)
    startup, rates = peer_rates(runs)
    rates = {p: r * rate_factor for p, r in rates.items()}
    lo, hi = 1, 10**6
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if peer_seconds(mid, startup, rates) <= target else (lo, mid - 1)
    end_s, end_n = log[-1]
    if lo <= end_n:  # the latest run ended early with end_n steps: more, at the pace it ended with
        lo = int(end_n + final_rate(log) * (target - end_s))
    return lo


def bracketed(target: float, tries: list[tuple[int, float]]) -> int | None:
    """n for a run ending at `target` seconds (the budget: segs's runs under the schedules' floor
    end at theirs), interpolated linearly between the tries (n, seconds from launch) that ended
    nearest below and nearest above it; None without such a pair or where they disagree (more
    iterations in less time: the host's speed changed). OpenSplat densifies until n / 2, so its
    pace depends on n, and the latest run's log alone sizes the next run too long after a short
    one and too short after a long one (the sample at 2 minutes: 3,130 iterations in 95 s, then
    3,598 in 161 s)."""
    below = [t for t in tries if t[1] < target]
    above = [t for t in tries if t[1] >= target]
    if not below or not above:
        return None
    (n0, s0), (n1, s1) = max(below, key=lambda t: t[1]), min(above, key=lambda t: t[1])
    if n1 <= n0:
        return None
    return int(round(n0 + (n1 - n0) * (target - s0) / (s1 - s0)))  # s0 < target <= s1


def final_rate(log: list) -> float:
    """Steps/s of a run's log [[seconds, step], ...] over the last half of the steps of the
    resolution phase it ended in (its whole log's mean rate where that is too short)."""
    pts = _phase_points(log, peer_phase(int(log[-1][1])))
    if len(pts) >= 3 and pts[-1][0] > pts[len(pts) // 2][0]:
        return _late_rate(pts)
    return (log[-1][1] - log[0][1]) / max(log[-1][0] - log[0][0], 1e-6)


def segs_steps(budget_s: float, runs: list[dict], rate_factor: float = 1.0) -> int:
    """max_steps for a segs run of budget_s: the latest run's steps per training second after
    its first step x rate_factor (below 1 after the pilot alone: its map is smaller), times the
    budget's seconds after startup, times AIM. For a longer run than the latest the rate is
    extrapolated (`segs_rate_trend`): its map grows, and its steps slow down."""
    r = runs[-1]
    seconds = (budget_s - r["startup_s"]) * AIM
    rate = r["steps"] / max(r["train_s"] - r["startup_s"], 1e-6) * rate_factor * segs_rate_trend(runs, seconds)
    return max(int(rate * seconds), 1)


def segs_max_steps(budget_s: float, runs: list[dict], rate_factor: float = 1.0) -> int:
    """max_steps of a segs run of budget_s: segs_steps, or the schedules' floor where it is larger
    (the pilot's schedule_floor: mapping.min_schedule_steps of a coarse-to-fine run, else 0); the
    budget then stops the run inside the floor's schedules (module docstring)."""
    return max(segs_steps(budget_s, runs, rate_factor), runs[0].get("schedule_floor", 0))


def cut_anywhere(run: dict) -> bool:
    """Whether a segs run stopped at any step n is the run sized to n: its schedules were sized for
    the floor (max_steps not above it), which a run sized to n < floor has too. Records without
    schedule_floor: schedules longer than max_steps (the same condition)."""
    scheduled = run.get("scheduled_steps", 0)
    if "schedule_floor" in run:
        return 0 < run["schedule_floor"] == scheduled
    return scheduled > run.get("max_steps", float("inf"))


def segs_rate_trend(runs: list[dict], seconds: float) -> float:
    """Factor on the latest run's mean rate for a run of `seconds` after startup: rate ~ seconds^a,
    a fitted on the latest run and the latest before it that trained at most 3/4 as long (a in
    [-0.5, 0]: the mean rate falls as the map grows); 1 when there is no such pair, the pilot
    excluded, or the run is not longer than the latest."""
    def length(r: dict) -> float:
        return r["train_s"] - r["startup_s"]

    last = runs[-1]
    earlier = next((r for r in reversed(runs[1:-1]) if length(r) <= 0.75 * length(last)), None)
    if earlier is None or seconds <= length(last):
        return 1.0
    a = np.log((last["steps"] / length(last)) / (earlier["steps"] / length(earlier))) / np.log(length(last) / length(earlier))
    return float((seconds / length(last)) ** np.clip(a, -0.5, 0.0))


def fits(run: dict, budget_s: float) -> bool:
    """Whether a run used its budget: it ended within [FIT_LOW, FIT_HIGH] x budget and, for segs,
    it ran its schedules as sized: its max_steps ("schedule_done": the share of them run), or,
    stopped by the budget, the floor's schedules (cut_anywhere: one stopped at step n is the run
    sized to n steps; where the schedules end at max_steps, a run stopped early skipped their end)."""
    seconds = run["points"][-1]["seconds"]
    done = run["method"] == "opensplat" or run["schedule_done"] >= 1.0 or cut_anywhere(run)
    return done and FIT_LOW * budget_s <= seconds <= FIT_HIGH * budget_s
