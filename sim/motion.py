"""Analytic motion profiles of one rotary axis, evaluable at any time.

A profile is a list of constant-acceleration segments; its state at a time is
computed in closed form, never integrated tick by tick (virtual time may jump
by hours). Units are whatever the caller uses consistently (rad, rad/s, rad/s²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Segment:
    """Constant acceleration from ``start_s`` on: position, velocity and acceleration there."""

    start_s: float
    position: float
    velocity: float
    acceleration: float

    def at(self, time_s: float) -> tuple[float, float]:
        dt = time_s - self.start_s
        return (
            self.position + self.velocity * dt + 0.5 * self.acceleration * dt * dt,
            self.velocity + self.acceleration * dt,
        )


@dataclass(frozen=True)
class Profile:
    """Segments in time order; after the last one's ``end_s`` the axis rests (or cruises on)."""

    segments: tuple[Segment, ...]
    end_s: float

    def state(self, time_s: float) -> tuple[float, float]:
        """``(position, velocity)`` at ``time_s`` (before the start: the start state)."""
        current = self.segments[0]
        if time_s <= current.start_s:
            return current.position, current.velocity
        for segment in self.segments[1:]:
            if segment.start_s > time_s:
                break
            current = segment
        return current.at(time_s)

    def is_moving(self, time_s: float) -> bool:
        return time_s < self.end_s or self.segments[-1].velocity != 0.0

    @property
    def final_position(self) -> float:
        """Where the profile ends (meaningful when it ends at rest)."""
        return self.segments[-1].position


def rest(position: float, time_s: float) -> Profile:
    """Standing still at ``position``."""
    return Profile((Segment(time_s, position, 0.0, 0.0),), time_s)


def _braking(time_s: float, position: float, velocity: float, accel: float) -> list[Segment]:
    """Segments that bring ``velocity`` to zero at ``accel`` (empty when already at rest)."""
    if velocity == 0.0:
        return []
    return [Segment(time_s, position, velocity, -math.copysign(accel, velocity))]


def _append_rest(segments: list[Segment], time_s: float) -> Profile:
    end_position, _ = segments[-1].at(time_s) if segments else (0.0, 0.0)
    return Profile((*segments, Segment(time_s, end_position, 0.0, 0.0)), time_s)


def stop(profile: Profile, time_s: float, accel: float) -> Profile:
    """Decelerate from the state at ``time_s`` to rest at ``accel``."""
    position, velocity = profile.state(time_s)
    segments = _braking(time_s, position, velocity, accel)
    if not segments:
        return rest(position, time_s)
    return _append_rest(segments, time_s + abs(velocity) / accel)


def move(profile: Profile, time_s: float, target: float, v_max: float, accel: float) -> Profile:
    """Trapezoidal (or triangular) move from the state at ``time_s`` to rest at ``target``.

    A moving axis first brakes to rest, then moves; ``v_max`` and ``accel`` > 0.
    """
    braked = stop(profile, time_s, accel)
    start_s = braked.end_s
    start = braked.final_position
    distance = target - start
    v_peak = min(v_max, math.sqrt(abs(distance) * accel))
    if v_peak == 0.0:  # no distance, or one too small to move at any representable speed
        rest_at_target = Segment(start_s, target, 0.0, 0.0)
        return Profile((*braked.segments[:-1], rest_at_target), start_s)
    sign = math.copysign(1.0, distance)
    t_ramp = v_peak / accel
    t_cruise = (abs(distance) - v_peak * t_ramp) / v_peak
    segments = list(braked.segments[:-1])
    up = Segment(start_s, start, 0.0, sign * accel)
    cruise_start = start + sign * 0.5 * v_peak * t_ramp
    cruise = Segment(start_s + t_ramp, cruise_start, sign * v_peak, 0.0)
    down = Segment(
        start_s + t_ramp + t_cruise,
        target - sign * 0.5 * v_peak * t_ramp,
        sign * v_peak,
        -sign * accel,
    )
    end_s = start_s + 2.0 * t_ramp + t_cruise
    return Profile((*segments, up, cruise, down, Segment(end_s, target, 0.0, 0.0)), end_s)


def cruise(profile: Profile, time_s: float, velocity: float, accel: float) -> Profile:
    """Change to a constant ``velocity`` (velocity mode) from the state at ``time_s``."""
    position, v0 = profile.state(time_s)
    if velocity == v0:
        return Profile((Segment(time_s, position, v0, 0.0),), time_s)
    t_ramp = abs(velocity - v0) / accel
    ramp = Segment(time_s, position, v0, math.copysign(accel, velocity - v0))
    end_position, _ = ramp.at(time_s + t_ramp)
    return Profile((ramp, Segment(time_s + t_ramp, end_position, velocity, 0.0)), time_s + t_ramp)
