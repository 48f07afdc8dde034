"""Correspondence between two surfaces: through a template (human bodies), or learned descriptors,
functional maps and ZoomOut.

- :mod:`~zernet.operators.spectral` — the Laplace-Beltrami eigenbasis (robust-laplacian, eigsh), cached, and ZoomOut.
- :mod:`~zernet.matching.fmap` — the differentiable functional-map layer, point maps, ZoomOut, confidence.
- :mod:`~zernet.matching.shapes` — a surface made ready for matching (:func:`prepare_shape`).
- :mod:`~zernet.matching.model` — the descriptor model, its spec and file format, the shipped model.
- :mod:`~zernet.matching.template` — the template model: a classifier names where on a body each point lies.
- :mod:`~zernet.matching.consistency` — the repair of a template map: limbs read as another part mapped again.
- :mod:`~zernet.matching.match` — :func:`match_surfaces`: two surfaces in, a vertex map out.
- :mod:`~zernet.matching.bodies` — generated bodies in independent forms, with ground-truth maps.
- :mod:`~zernet.matching.train` — training the descriptor model (``python -m zernet.matching.train``).
- :mod:`~zernet.matching.train_template` — training a template model (``python -m zernet.matching.train_template``).

The method is explained in ``docs/MATCHING.md``.
"""

from zernet.matching.fmap import cycle_confidence, fmap_from_pointmap, functional_map, pointmap_from_fmap, zoomout
from zernet.matching.match import MatchResult, load_matcher, match_shapes, match_surfaces
from zernet.matching.model import PRETRAINED_MODEL, DescriptorModel, MatchingSpec, load_matching_model
from zernet.matching.template import PRETRAINED_TEMPLATE_MODEL, TemplateModel, load_template_model
from zernet.operators.spectral import SpectralBasis, laplacian_eigenbasis

__all__ = [
    "SpectralBasis",
    "laplacian_eigenbasis",
    "functional_map",
    "fmap_from_pointmap",
    "pointmap_from_fmap",
    "zoomout",
    "cycle_confidence",
    "MatchingSpec",
    "DescriptorModel",
    "load_matching_model",
    "PRETRAINED_MODEL",
    "TemplateModel",
    "load_template_model",
    "PRETRAINED_TEMPLATE_MODEL",
    "load_matcher",
    "MatchResult",
    "match_shapes",
    "match_surfaces",
]
