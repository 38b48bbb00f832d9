"""Reading measured free-decay traces from text files: :func:`load_trace` -> :class:`Trace`.

Real exports are messy: comma, semicolon, tab or whitespace separators, a header line or none,
Windows line ends, comment lines, separator lines ("-----"), empty trailing fields, a time
column that a data logger writes in buffers (many rows share one stamp). The reader accepts
all of that, and it never guesses silently: a row whose time or position cannot be read is
dropped and counted (``Trace.n_dropped``), and a file without usable rows is an error that
names the file and the columns.

With a header line the time and position columns are chosen by what their names mean (a
time: "t", "time", "Time_Elapsed(s)", a unit "(s)", before a clock "Timestamp"; a position:
"x", "position", "Angle(deg)", "displacement", a unit "(m)", "(deg)", "(rad)"; never a
velocity, an acceleration or an error column), so ``Timestamp, Time_Elapsed(s), Angle(deg)``
reads the angle against the elapsed time; a choice the names do not settle is a ValueError
naming the columns found. The chosen names are in ``Trace.time_column`` and
``Trace.position_column`` (and in its repr); columns given by the caller always win.
"""

from ._columns import column_unit as column_unit
from ._load import DROPPED_SHARE as DROPPED_SHARE
from ._load import MAX_TRACE_BYTES as MAX_TRACE_BYTES
from ._load import Trace as Trace
from ._load import load_trace as load_trace
from ._load import read_regular_file as read_regular_file
