"""Metric 3D pose of instruments from one calibrated camera (beyond the paper).

The shaft is a cylinder of known diameter: its two silhouette (limb) lines and the camera
intrinsics give its 3D axis in closed form; the shaft-clasper boundary gives the joint J
on that axis; the clasper's far end and its known length give the tip. Over a sequence,
the axes' common point (the trocar) and temporal filtering stabilise the estimates.

Public API:

- :func:`measure_instance`: one instrument in one frame (pure, thread-safe).
- :func:`refine_sequence`: trocar, trocar constraint, temporal filtering over a table.

Conventions: camera frame OpenCV (x right, y down, z forward), millimetres; ``end_*``
is a part's distal end (shaft: J; clasper: tip), ``start_*`` its proximal end (shaft:
where the axis leaves the view, or the shaft's visible proximal end; clasper: J);
``axis_*`` unit, distal; ``qw..qz`` the wxyz quaternion of a part frame whose +z is the
axis (shortest arc from the camera's +z: roll about the shaft is not observable from
masks); ``quality`` the IoU of the re-rendered part with its mask. NaN = unknown.
"""

from mistool.pose.measure import measure_instance
from mistool.pose.refine import refine_sequence

__all__ = ["measure_instance", "refine_sequence"]
