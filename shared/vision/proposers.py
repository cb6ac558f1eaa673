"""Who found a tag: stage 1's proposers (shared.vision.proposals: AprilTag decimated, its
full-resolution sweep and windows, OpenCV's ArUco, the line quads' hard decode and their blind soft
decode) or the tracker (shared.vision.tracking). A name only, so the wire layer can carry it without
importing any detector."""

from __future__ import annotations

from typing import Literal

Proposer = Literal["apriltag", "fullres", "aruco", "lines", "lines_soft", "tracker"]
