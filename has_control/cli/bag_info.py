"""``has-control bag-info``: topics, types, counts and duration of a bag, and
how its recorded samples read (layout, grid, drops, repeats)."""
from __future__ import annotations

from has_control.cli.args import add_reading, reading_of

from has_control.bag import PARAMETERS_KEY, describe, read_bag
from has_control.bag.base import warnings_as_lines
from has_control.bag.recorded import read_recording
from has_control.common.errors import HasControlError


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG")
    add_reading(p)


@warnings_as_lines()
def run(args) -> int:
    bag = read_bag(args.bag)
    print(describe(bag))
    notes: list[str] = []
    bag.on_warning = notes.append
    try:
        step = bag.config().episode.step if PARAMETERS_KEY in bag.custom_data else None
        rec = read_recording(bag, step, reading_of(args))
    except HasControlError as exc:
        print(f"Samples:           not readable as a run ({str(exc).removeprefix(str(bag.path) + ': ')})")
        return 0
    print(f"Layout:            {rec.layout} (states {rec.state_topic}, commands {rec.command_topic or 'none'}"
          + (f": {rec.rule}" if rec.rule else "") + ")")
    print(f"Samples:           {int(rec.state.sum())} states, {int(rec.command.sum())} commands on the "
          f"{rec.step * 1e3:g} ms grid, {len(rec.dropped)} dropped")
    for line in notes:
        print(f"  {line.removeprefix(str(bag.path) + ': ')}")
    return 0
