"""Images made from events for a detector (eventcap/imaging/event_images.py) and the stage's choice among them."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.events import make_events
from eventcap.imaging.event_images import count_image, event_image, parse_kind, surface_image


def _bar_events():
    """A vertical bar at x = 10..12 firing every ms from 0 to 49 ms, plus one event at x = 30 at 5 ms."""
    t = np.repeat(np.arange(50) * 1000, 3)
    x = np.tile([10, 11, 12], 50)
    ev = make_events(np.concatenate([t, [5000]]), np.concatenate([x, [30]]), np.full(151, 8), np.ones(151))
    order = np.argsort(ev["t"], kind="stable")
    return ev[order]


def test_parse_kind_and_its_errors():
    assert parse_kind("reconstruction") == ("reconstruction", 0)
    assert parse_kind("counts:25") == ("counts", 25000) and parse_kind("surface:50") == ("surface", 50000)
    for bad, msg in (("edges:10", "expected one of"), ("counts", "whole milliseconds"), ("counts:0", r"\[1, 500\]"),
                     ("surface:x", "whole milliseconds"), ("reconstruction:5", "takes no window")):
        with pytest.raises(ValueError, match=msg):
            parse_kind(bad)


def test_count_image_is_dark_where_events_fired_in_the_window():
    ev = _bar_events()
    im = count_image(ev, 49_000, 20_000, 16, 40)
    assert im.shape == (16, 40) and im.dtype == np.float32
    assert (im[8, 10:13] == 0.0).all()  # 20 events each: the darkest
    assert im[8, 30] == 1.0  # its event at 5 ms lies outside the last 20 ms
    assert (np.delete(im, [10, 11, 12], axis=1) == 1.0).all()
    assert (count_image(ev, 200_000, 10_000, 16, 40) == 1.0).all()  # no events: white


def test_surface_image_is_darkest_where_the_last_event_is_oldest_within_the_window():
    ev = _bar_events()
    im = surface_image(ev, 60_000, 30_000, 16, 40)
    # the bar last fired at 49 ms: age 11 ms, tau 10 ms
    assert np.allclose(im[8, 10:13], 1 - np.exp(-1.1), atol=1e-6)
    assert im[8, 30] == 1.0 and im[0, 0] == 1.0
    assert event_image("surface:30", ev, 60_000, 16, 40).tolist() == im.tolist()
    rec = np.full((16, 40), 0.5, np.float32)
    assert event_image("reconstruction", ev, 0, 16, 40, reconstruction=rec) is rec
