"""The SITL's counters of rejected actuator input and its one-line status report."""

from __future__ import annotations

from dataclasses import dataclass, fields

from bridge.stats import LinkStats


@dataclass
class CommandStats:
    """What the SITL refused or repaired in actuator input (beyond the link's frame-level drops)."""

    commands: int = 0  # HIL_ACTUATOR_CONTROLS accepted and applied
    stale: int = 0  # not stamped with a HIL_SENSOR's time_usec (lockstep: the last one; real time: since
    #                  the last applied)
    nonfinite: int = 0  # throttles that were NaN or infinite (treated as 0)
    clamped: int = 0  # throttles outside [0, 1] (clamped)
    ignored: int = 0  # valid frames of other message ids (not HEARTBEAT or HIL_ACTUATOR_CONTROLS)
    failsafes: int = 0  # times the failsafe engaged
    foreign: int = 0  # frames from another sender than the bound companion (ignored)
    resent: int = 0  # lockstep steps re-sent because their reply was late (0.1 s) or lost

    def as_dict(self) -> dict[str, int]:
        """All counters as a plain dict."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class StatusSnapshot:
    """Everything one status line shows."""

    sim_time_s: float
    steps: int
    steps_per_s: float  # over the last status interval, wall clock
    realtime_factor: float  # simulated s per wall s over the last interval
    mode: str  # lockstep | realtime
    phase: str  # waiting | starting | stepping | failsafe
    companion: tuple[str, int] | None
    position: tuple[float, float, float]  # NED, m
    link: LinkStats
    commands: CommandStats


def format_status(s: StatusSnapshot) -> str:
    """One line: time, speed, mode, companion, position, link and command counters, failsafe state."""
    who = f"{s.companion[0]}:{s.companion[1]}" if s.companion else "none"
    n, e, d = s.position
    c = s.commands
    link = s.link
    drops = link.drops()
    drop_text = " ".join(f"{k}={v}" for k, v in drops.items()) or "none"
    return (
        f"quadsr sitl: t={s.sim_time_s:.3f}s steps={s.steps} rate={s.steps_per_s:.0f}/s "
        f"rtf={s.realtime_factor:.2f} "
        f"mode={s.mode} phase={s.phase} companion={who} pos_ned=({n:.3f},{e:.3f},{d:.3f})m "
        f"hil: sent={link.frames_sent} recv={link.frames_received} dropped={link.dropped} [{drop_text}] "
        f"cmds={c.commands} stale={c.stale} nonfinite={c.nonfinite} clamped={c.clamped} ignored={c.ignored} "
        f"foreign={c.foreign} resent={c.resent} failsafe={'ON' if s.phase == 'failsafe' else 'off'} "
        f"failsafes={c.failsafes}"
    )


def parse_status(line: str) -> dict[str, str]:
    """The key=value pairs of a status line (for tests and scripts)."""
    out: dict[str, str] = {}
    for token in line.replace("[", " ").replace("]", " ").split():
        if "=" in token:
            key, _, value = token.partition("=")
            out[key] = value
    return out
