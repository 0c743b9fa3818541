"""Reading and writing event-camera recordings, robust to bad input: an error names the file, the row or offset
and what was expected (the shared checks and repairs are in :mod:`eventcap.io.checks`).

Formats (detected from the content, then the extension; or ``format=``): every reader declares its own in
:mod:`eventcap.io.registry` (``eventcap formats`` prints them): AEDAT4, AEDAT 2.0 and 3.1, HDF5, rpg folders and
csv/txt, Prophesee EVT 2.0 / 3.0 and DAT (our own decoders, :mod:`eventcap.io.evt`), npy/npz; plugins add theirs
through the ``eventcap.readers`` entry points or ``EVENTCAP_READERS``.

Layout options of :func:`read_recording` / :func:`iter_event_chunks`: ``columns=`` names the column order of
unnamed (N, 4) or (4, N) arrays (C or Fortran order) and text files (e.g. ``"x,y,t,p"``; a csv's first line of
names does the same), ``time_unit=`` the unit of their time column, ``y_up=True`` flips a bottom-up y axis.

Everything comes out in the project's conventions: ``EVENT_DTYPE`` events sorted by time, µs since the first
event (the file's time of that event is ``t_offset_us``), polarity ±1, coordinates inside the sensor; frames as
float32 in [0, 1] with exposure-centre times on the same clock.

Bad input either loads with every repair listed in ``RawRecording.repairs`` (and logged as a warning on the
``eventcap.io`` logger) or raises :class:`RecordingError` (a ``ValueError``) naming the file, the position (line,
event index, packet, dataset) and the problem. docs/io-robustness.md says it to users, format by format:

- time (:class:`eventcap.io.checks.TimeGuard`, in file order, the same streaming or whole): a few events cut off
  by jumps in time (a wild timestamp, stray first or last events) dropped; a jump of a decoder's counter range
  undone; time standing still after a jump cut; other jumps beyond ``max_gap_s`` (60 s) refused with the event
  index; more events per µs than any sensor refused; a time column of whole numbers whose unit is a guess and
  whose first events come slower than any camera's refused, naming ``source.time_unit``;
- sizes inferred from coordinates (:mod:`eventcap.io.sizes`): outliers beyond a gap, beyond every known sensor or
  beyond the edge of a known sensor's block are dropped when few and refused otherwise, never taken as a wider
  sensor; an inferred size that is no sensor's shape is refused;
- repaired as well: events out of time order (sorted), exact duplicate events (equal as the file holds them:
  dropped), 32-bit timestamp
  wrap-around (unwrapped), a truncated tail (the complete part kept: AEDAT4 packets, npy rows, a text line, a
  partial EVT/DAT word, an EVT3 event group left open), unnamed (N, 4) columns (recognised by the time-ordered
  column), colour frames (to grey), unsorted or repeated frame times, a corrupt compressed AEDAT4 packet (skipped);
- refused as well: paths that are not regular files or folders (pipes, devices, link loops: at once, never
  opened), empty or unrecognised files (a file whose extension promises a signature it lacks), a damaged
  ``zarr.json``, missing datasets or keys, coordinates outside a declared sensor, negative or non-integer
  coordinates, non-finite times, polarity values outside {0, 1} / {-1, +1} or mixing them, corrupted containers
  (whatever the decoding library reports; HDF5 structure read first in a forked probe, refused if the library
  loops), EVT data whose words carry event types the format does not define, corrupted AEDAT 3.1 packet headers.

EVT and DAT times are decoded by our own code: every event at the time the file gives it, never clamped (a time
going backwards is sorted or dropped with a note like any other format's). Declared sizes (zarr and HDF5 shapes,
AEDAT packet sizes) are checked against the bytes before anything is allocated. Decoding libraries' panics are
caught; the fuzz script
``benchmarks/robustness/fuzz_readers.py`` checks that no damaged file of any format is read silently wrong, hangs
or ends in a traceback.
"""

from eventcap.io.detect import detect_format
from eventcap.io.readers import EventChunks, Roi, iter_event_chunks, read_recording
from eventcap.io.registry import ReaderSpec, readers
from eventcap.io.recording import Frames, RawRecording, RecordingError
from eventcap.io.writers import WRITE_FORMATS, write_events, write_recording

__all__ = [
    "ReaderSpec",
    "readers",
    "WRITE_FORMATS",
    "EventChunks",
    "Frames",
    "RawRecording",
    "RecordingError",
    "Roi",
    "detect_format",
    "iter_event_chunks",
    "read_recording",
    "write_events",
    "write_recording",
]


def __getattr__(name: str):
    if name == "READ_FORMATS":  # the formats format= takes, from the registry
        return tuple(readers().names())
    raise AttributeError(name)
