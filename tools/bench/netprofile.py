"""Network profiles for the link between the console site and the slave site, emulated in user space.

A :class:`LinkProfile` says what one direction of the link does to each packet: a one-way delay
with jitter, random or bursty loss (Gilbert–Elliott), a bandwidth cap (token bucket with a
packet queue), reordering and scheduled outages. :data:`PROFILES` names the distances the
project cares about, each value with its source. :class:`LinkModel` applies a profile to a
stream of packets — a pure function of arrival times, sizes and a seed, no I/O — and
:class:`~telesurg.tools.bench.impair.PacketLink` runs one model per direction on real packets.

One option set serves every tool that drives a link (``telesurg impair``, ``telesurg bench
transport``): :func:`add_profile_args` and :func:`profile_from_args`::

    telesurg bench transport --profile 5g-microhand
    telesurg impair --profile lindbergh --jitter-ms 5

Example::

    model = LinkModel(profile("5g-microhand", burst=3), seed=1)
    due = model.admit(now_s, 128)    # departure time in s, or why it was dropped ("loss", ...)
"""

from __future__ import annotations

import argparse
import math
import random
from dataclasses import dataclass, fields, replace
from typing import Literal

from telesurg.shared.errors import ConfigError

Jitter = Literal["uniform", "normal"]
#: why :meth:`LinkModel.admit` dropped a packet
DropReason = Literal["loss", "queue", "outage"]


@dataclass(frozen=True)
class LinkProfile:
    """What one direction of the link does to every packet (the other direction: the same).

    The Gilbert–Elliott loss model has a good state (no loss) and a bad state (every packet
    lost); ``loss`` is the mean loss and ``burst`` the mean number of packets lost in a row,
    so P(good → bad) = ``loss`` / (``burst`` · (1 − ``loss``)) and P(bad → good) = 1 / ``burst``.
    ``burst`` 1 is independent loss.
    """

    delay_ms: float = 0.0  # one-way delay, ms: half the round trip the sites see
    jitter_ms: float = 0.0  # ± this per packet (uniform) or its σ (normal), ms; FIFO kept
    jitter: Jitter = "uniform"  # distribution of the per-packet jitter
    loss: float = 0.0  # mean packet loss, 0..1 (exclusive)
    burst: float = 1.0  # mean loss-burst length, packets (1: independent losses)
    rate_kbps: float = 0.0  # bandwidth cap on IP packet bytes, kbit/s (0: none)
    queue: int = 100  # packets that may wait for the cap; one more is dropped (tail drop)
    bucket_bytes: int = 3000  # token-bucket depth, bytes: a burst that passes at line speed
    reorder: float = 0.0  # fraction of packets held back ``reorder_ms`` more (they arrive late)
    reorder_ms: float = 10.0  # extra delay of a reordered packet, ms
    outage_ms: float = 0.0  # length of each scheduled outage (every packet dropped), ms
    outage_every_s: float = 10.0  # an outage starts this long after the link starts, then again

    def __post_init__(self) -> None:
        problems = []
        for name in ("delay_ms", "jitter_ms", "rate_kbps", "reorder_ms", "outage_ms"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                problems.append(f"{name} must be a finite number >= 0, got {v!r}")
        for name in ("loss", "reorder"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                problems.append(f"{name} must be in [0, 1), got {v!r}")
        if not (math.isfinite(self.burst) and self.burst >= 1.0):
            problems.append(f"burst must be a mean burst length >= 1 packet, got {self.burst!r}")
        if self.jitter not in ("uniform", "normal"):
            problems.append(f"jitter must be uniform or normal, got {self.jitter!r}")
        if self.queue < 1 or self.bucket_bytes < 1:
            problems.append(f"queue and bucket_bytes must be >= 1, got {self.queue}, {self.bucket_bytes}")
        if self.outage_ms > 0 and not (
            math.isfinite(self.outage_every_s) and self.outage_every_s * 1000.0 > self.outage_ms
        ):
            problems.append(
                f"outage_every_s ({self.outage_every_s!r}) must be longer than "
                f"an outage ({self.outage_ms} ms)"
            )
        if problems:
            raise ConfigError("bad link profile: " + "; ".join(problems))

    @property
    def p_good_bad(self) -> float:
        """Gilbert–Elliott P(good → bad) per packet."""
        return self.loss / (self.burst * (1.0 - self.loss)) if self.loss > 0 else 0.0

    @property
    def p_bad_good(self) -> float:
        """Gilbert–Elliott P(bad → good) per packet."""
        return 1.0 / self.burst

    @classmethod
    def from_transitions(
        cls, p_good_bad: float, p_bad_good: float, **others: float | int | str
    ) -> LinkProfile:
        """The profile of a Gilbert–Elliott chain given by its transition probabilities per packet
        (every packet lost in the bad state, none in the good one): mean loss
        p_gb / (p_gb + p_bg), mean burst 1 / p_bg.

        Raises:
            ConfigError: a probability outside (0, 1], or a mean loss of 1.
        """
        if not (0.0 < p_good_bad <= 1.0 and 0.0 < p_bad_good <= 1.0):
            raise ConfigError(
                "Gilbert–Elliott transition probabilities must be in (0, 1], "
                f"got {p_good_bad!r}, {p_bad_good!r}"
            )
        loss = p_good_bad / (p_good_bad + p_bad_good)
        return cls(loss=loss, burst=1.0 / p_bad_good, **others)  # type: ignore[arg-type]

    def describe(self) -> str:
        """One line: the non-default values, e.g. ``delay 57 ms, loss 1.2 %``."""
        parts = [f"delay {self.delay_ms:g} ms"]
        if self.jitter_ms:
            parts.append(f"jitter ±{self.jitter_ms:g} ms {self.jitter}")
        if self.loss:
            parts.append(
                f"loss {100 * self.loss:g} %" + (f" in bursts of {self.burst:g}" if self.burst > 1 else "")
            )
        if self.rate_kbps:
            parts.append(f"cap {self.rate_kbps:g} kbit/s (queue {self.queue})")
        if self.reorder:
            parts.append(f"reorder {100 * self.reorder:g} % by +{self.reorder_ms:g} ms")
        if self.outage_ms:
            parts.append(f"outage {self.outage_ms:g} ms every {self.outage_every_s:g} s")
        return ", ".join(parts)


#: Named profiles: one-way values (a round trip is twice the delay).
PROFILES: dict[str, LinkProfile] = {
    # a switched gigabit LAN: ping RTT ≈ 0.4 ms between two hosts on one switch
    "lan": LinkProfile(delay_ms=0.2),
    # hinotori (Medicaroid) remote-surgery trial over ~30 km of dedicated fibre: 27 ms RTT
    "fibre-30km": LinkProfile(delay_ms=13.5),
    # MicroHand 5G telesurgery trial over ~3,000 km: 114 ms RTT, 1.2 % packet loss (independent:
    # the trial gives no burst length; --burst sets one)
    "5g-microhand": LinkProfile(delay_ms=57.0, loss=0.012),
    # a transoceanic route (e.g. Europe – East Asia): ~200 ms RTT
    "intercontinental": LinkProfile(delay_ms=100.0),
    # Operation Lindbergh (New York – Strasbourg, 2001, Marescaux et al., Nature 413:379):
    # 150 ms RTT over dedicated ATM, ±10 ms jitter
    "lindbergh": LinkProfile(delay_ms=75.0, jitter_ms=10.0),
}


def profile(name: str = "", **overrides: float | int | str) -> LinkProfile:
    """The named profile (``""``: a perfect link) with ``overrides`` applied.

    Raises:
        ConfigError: unknown name (the message names the valid ones) or a bad value.
    """
    if name and name not in PROFILES:
        raise ConfigError(f"unknown link profile {name!r}; valid: {', '.join(PROFILES)}")
    base = PROFILES[name] if name else LinkProfile()
    known = {f.name for f in fields(LinkProfile)}
    if bad := sorted(set(overrides) - known):
        raise ConfigError(f"unknown link profile field(s) {bad}; valid: {', '.join(sorted(known))}")
    return replace(base, **overrides)  # type: ignore[arg-type]


# --------------------------------------------------------------------- the model


class LinkModel:
    """One direction of a link: decides, per packet, when it leaves or why it is dropped.

    Pure: the caller gives each packet's arrival time (s, any monotonic clock) and size (bytes);
    the same seed and the same arrivals give the same decisions. Steps, in order: a scheduled
    outage drops it; Gilbert–Elliott loss drops it; the token bucket holds it until it has the
    tokens (dropped when ``queue`` packets already wait); then the delay with jitter, never
    before an earlier packet (FIFO) unless it is picked for reordering (``reorder_ms`` extra,
    others do not wait for it).

    Args:
        prof: the profile.
        seed: seed of the random parts (None: a fresh one).
        start: the link's start time, s (outages count from it; default: the first packet).
    """

    def __init__(self, prof: LinkProfile, seed: int | str | None = None, start: float | None = None) -> None:
        self.profile = prof
        self._rng = random.Random(seed)
        self._start = start
        self._bad = False  # Gilbert–Elliott state
        self._last_due = -math.inf  # departure of the newest in-order packet (FIFO floor)
        self._tokens = float(prof.bucket_bytes)
        self._shaped_at = -math.inf  # departure from the bucket of the last packet
        self._waiting: list[float] = []  # bucket departures still ahead (queue occupancy)

    def reconfigure(self, prof: LinkProfile, start: float | None = None) -> None:
        """Switch to ``prof``; packets already admitted keep their times, order is kept."""
        self.profile = prof
        if start is not None:
            self._start = start
        self._tokens = min(self._tokens, float(prof.bucket_bytes))

    def in_outage(self, now: float) -> bool:
        """True while a scheduled outage is on at ``now``."""
        p = self.profile
        if p.outage_ms <= 0 or self._start is None:
            return False
        t = now - self._start
        return t >= p.outage_every_s and (t % p.outage_every_s) < p.outage_ms / 1000.0

    def admit(self, now: float, size: int) -> float | DropReason:
        """The departure time (s) of a packet of ``size`` bytes arriving at ``now``, or the drop reason."""
        p = self.profile
        if self._start is None:
            self._start = now
        if self.in_outage(now):
            return "outage"
        if p.loss > 0:
            rng = self._rng.random()
            if self._bad:
                self._bad = rng >= p.p_bad_good
            else:
                self._bad = rng < p.p_good_bad
            if self._bad:
                return "loss"
        out = now
        if p.rate_kbps > 0:
            while self._waiting and self._waiting[0] <= now:
                self._waiting.pop(0)
            if len(self._waiting) >= p.queue:
                return "queue"
            rate = p.rate_kbps * 125.0  # bytes/s
            start = max(now, self._shaped_at)
            if self._shaped_at > -math.inf:
                self._tokens = min(float(p.bucket_bytes), self._tokens + (start - self._shaped_at) * rate)
            need = min(float(size), float(p.bucket_bytes))  # a packet larger than the bucket: its size
            if self._tokens >= need:
                out = start
                self._tokens -= size
            else:
                out = start + (need - self._tokens) / rate
                self._tokens = need - size
            self._shaped_at = out
            self._waiting.append(out)
        delay = p.delay_ms
        if p.jitter_ms > 0:
            if p.jitter == "uniform":
                delay += self._rng.uniform(-p.jitter_ms, p.jitter_ms)
            else:
                delay += self._rng.gauss(0.0, p.jitter_ms)
        due = out + max(0.0, delay) / 1000.0
        if p.reorder > 0 and self._rng.random() < p.reorder:
            return due + p.reorder_ms / 1000.0  # late, and nothing waits for it
        due = max(due, self._last_due)
        self._last_due = due
        return due


# --------------------------------------------------------------------- the shared options


def add_profile_args(
    parser: argparse.ArgumentParser, *, delay_default: float | None = None, loss: bool = True
) -> None:
    """Add ``--profile`` and its overrides to ``parser`` (read back with :func:`profile_from_args`).

    ``loss=False`` leaves ``--loss`` to the caller (a bench that sweeps several loss rates).
    """
    g = parser.add_argument_group("link profile (each value one way, per direction)")
    g.add_argument(
        "--profile", default="", metavar="NAME", help=f"one of {', '.join(PROFILES)} (default: none)"
    )
    dflt = f" (default {delay_default:g})" if delay_default is not None else ""
    g.add_argument("--delay-ms", type=float, metavar="MS", help=f"one-way delay, ms{dflt}")
    g.add_argument("--jitter-ms", type=float, metavar="MS", help="± jitter per packet, ms (FIFO kept)")
    g.add_argument("--jitter", choices=("uniform", "normal"), help="jitter distribution (default uniform)")
    if loss:
        g.add_argument("--loss", type=float, metavar="P", help="mean packet loss, 0..1")
    g.add_argument(
        "--burst", type=float, metavar="N", help="mean loss-burst length, packets (Gilbert–Elliott)"
    )
    g.add_argument("--rate-kbps", type=float, metavar="KBPS", help="bandwidth cap, kbit/s (0: none)")
    g.add_argument("--queue", type=int, metavar="N", help="packets that may wait for the cap (default 100)")
    g.add_argument("--reorder", type=float, metavar="P", help="fraction of packets delayed --reorder-ms more")
    g.add_argument(
        "--reorder-ms", type=float, metavar="MS", help="extra delay of a reordered packet (default 10)"
    )
    g.add_argument("--outage", metavar="MS[/EVERY_S]", help="an outage of MS every EVERY_S s (default 10)")


def profile_from_args(
    args: argparse.Namespace, *, delay_default: float = 0.0, loss: bool = True
) -> LinkProfile:
    """The profile the options of :func:`add_profile_args` describe (``loss=False``: not ``--loss``).

    Raises:
        ConfigError: unknown profile or a bad value (one line, naming the valid options).
    """
    over: dict[str, float | int | str] = {}
    for name in (
        "delay_ms",
        "jitter_ms",
        "jitter",
        "loss",
        "burst",
        "rate_kbps",
        "queue",
        "reorder",
        "reorder_ms",
    ):
        v = getattr(args, name, None) if loss or name != "loss" else None
        if v is not None:
            over[name] = v
    if not args.profile and "delay_ms" not in over:
        over["delay_ms"] = delay_default
    if args.outage:
        text, _, every = str(args.outage).partition("/")
        try:
            over["outage_ms"] = float(text)
            if every:
                over["outage_every_s"] = float(every)
        except ValueError:
            raise ConfigError(f"--outage wants MS or MS/EVERY_S (e.g. 500/10), got {args.outage!r}") from None
    return profile(args.profile, **over)
