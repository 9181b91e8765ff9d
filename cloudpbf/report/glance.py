"""The report's first screen: one card per verdict, each a small figure, a one-line answer and the error or
interval it holds with, and links to the section and the data files behind it.

The studies make the cards (each declares ``GlanceCard``s in its registration, cloudpbf.report.catalogue); this
module holds what they share: the card (:class:`Card`), its links, the wording of a speed-up with its interval,
and :func:`summary`, which draws the declared cards in order.  A card without data says which command produces
it.

Verdict rules the cards share: every speed-up beside its interval, and "no difference measured" where the
interval holds 1 (or 0 for a difference) (:func:`ratio_words`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .catalogue import GlanceCard
from .common import Inputs, Section, _command
from .inference import LEVEL, Interval, describes_no_difference


@dataclass
class Card:
    id: str
    title: str
    answer: str = ""
    detail: str = ""
    figure: str | None = None
    links: list = field(default_factory=list)      # (label, href): sections '#id', data files 'data/NAME'
    level: str = "ok"                              # ok, warn (no difference measured / caveat), missing
    command: str = ""


def data_link(inp: Inputs, *names: str) -> list:
    return [(name, f"data/{name}") for name in names if (inp.data / name).is_file()]


def section_link(target: str, titles: dict) -> list:
    return [(titles[target], f"#{target}")] if target in titles else []


def missing_card(card: Card, inp: Inputs, what: str, key: str) -> Card:
    card.level, card.answer, card.command = "missing", f"not run in this study: {what}", _command(key, inp)
    return card


def ratio_words(ci: Interval, what: str = "", interval: str = f"{100 * LEVEL:g}% interval") -> str:
    """'1.60x faster [1.30, 1.90]' or 'no difference measured (1.05x, 95% interval 0.8-1.3x)'; `interval` names
    the interval (a t-interval, or the 5-95% of resampled seeds)."""
    if describes_no_difference(ci):
        bounds = (f", {interval} {ci.lo:.2f}-{ci.hi:.2f}x" if np.isfinite(ci.lo) else ", no interval")
        return f"no difference measured ({ci.mean:.2f}x{bounds})"
    if ci.mean >= 1:
        return f"{ci.mean:.2f}x faster{what} [{ci.lo:.2f}, {ci.hi:.2f}]"
    return f"{1 / ci.mean:.2f}x slower{what} [{1 / ci.hi:.2f}, {1 / ci.lo:.2f}]"


RESAMPLED = "5-95% over resampled seeds"


def resampled(value, interval, seeds) -> Interval:
    """A speed-up with its 5-95% interval over resampled seeds (NaN bounds where the study recorded none)."""
    lo, hi = (float(v) for v in interval) if interval else (math.nan, math.nan)
    return Interval(float(value), lo, hi, int(seeds or 0))


def _failed(build, exc: Exception) -> Card:
    name = getattr(build, "__name__", "card").replace("_card", "")
    return Card(name, name.replace("_", " "),
                answer=f"could not build this card from data/: {type(exc).__name__}: {exc}", level="missing")


def summary(inp: Inputs, sec: Section, env: dict | None, cards: tuple[GlanceCard, ...], titles: dict) -> None:
    """The verdict cards (the report's first screen), in the order the studies declared them.  Of the cards of one
    slot, the first that shows data is drawn, else the first that says what is missing."""
    slots: dict = {}
    for entry in sorted(cards, key=lambda c: c.order):
        slots.setdefault(entry.slot or id(entry), []).append(entry)
    shown = []
    for chain in slots.values():
        missing = None
        for entry in chain:
            try:
                card = entry.build(inp, env, titles)
            except Exception as exc:  # a broken input must not hide the other cards
                card = _failed(entry.build, exc)
            if card is None:
                continue
            if card.level != "missing":
                shown.append(card)
                break
            missing = missing or card
        else:
            if missing is not None:
                shown.append(missing)
    sec.add("cards", shown)
