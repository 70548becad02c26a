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

Temporal filtering (``refine_sequence(smoothing=...)``, ``mistool.track(smoothing=...)``):
``"offline"`` (default) a zero-phase constant-velocity Kalman smoother (forward filter +
Rauch-Tung-Striebel backward pass) for recorded sequences; ``"online"`` the causal forward
filter only (no lag from the future; the trocar constraint, which needs the whole
sequence, is not applied); ``"none"`` per-frame estimates (with the trocar constraint).

Known limits (measured by ``scripts/eval_metric.py``): the depth comes from the shaft's
apparent width, so a segmentation that is uniformly too fat or too thin by ``b`` px
scales the depth by about ``1 - b * z / (f r)`` (median J error at 50-150 mm with mild
corruption: ~1.2 mm for 0.5 px, ~2.3 mm for 1 px, either sign; ``mistool synth --bias``
renders such a bias sub-pixel exactly); the tip's depth along its viewing ray relies on
priors (the clasper's length and a small bend from the shaft), so strong wrist bends out
of the image plane and open jaws (shorter than the nominal length) cost a millimetre or
more; two tools touching in a merged mask yield the larger shaft's pose and no clasper
pose.
"""

from mistool.pose.measure import measure_instance
from mistool.pose.refine import refine_sequence

__all__ = ["measure_instance", "refine_sequence"]
