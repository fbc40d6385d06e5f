"""Checks of a mesh against Theorem 6, independently of the refinement: the steps written once
(``steps.run_checks``) over each domain's answers (``domains.<domain>.certify``: a
``Geometry`` of the mesh and the ``Points``' questions in each); what the box domains share
is in ``common``, the ``Certificate`` in ``certificate``. Nothing here calls the refinement
kernels: counts and distances come from kd-trees. ``knnrefine.certify`` (``api.certify``)
checks its options and calls ``pipeline.certify_points`` in this process, or
``scale.checks`` strip by strip in worker processes (the same steps, the points' questions
asked where they are)."""

from .certificate import Certificate
from .common import check_precondition, check_source

__all__ = [
    "Certificate",
    "check_source",
    "check_precondition",
]
