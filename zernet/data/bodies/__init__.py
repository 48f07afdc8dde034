"""Human bodies with ground truth, generated offline by the parametric body model ``anny``.

``anny`` (Apache-2.0 code, CC0 MakeHuman assets) is an optional dependency, imported lazily by this module
only: ``pip install 'zernet[bodies]'``. Every body of a data set shares one connectivity, so the
correspondence class of a vertex is its index (as for FAUST), and each vertex carries one of the 8 part
labels of the human-segmentation benchmark (Maron et al. 2017).

Topologies (``topology=``)
    ==============  ========  =================================================================
    name            vertices  made from
    ==============  ========  =================================================================
    ``faust``       6,890     the full body decimated once (quadric decimation, fast-simplification)
                              to FAUST's count (6,890 vertices, 13,776 faces); every kept vertex is
                              a point of the full template in barycentric coordinates of one of its
                              triangles, carried through every posed body
    ``full``        12,408    anny's template without its interior parts (eyes, tongue) and with its
                              mouth and eye sockets closed (below)
    ``coarse-1229`` 1,229     anny's shipped ``notoes_collapse10pc`` topology
    ``coarse-615``  615       anny's shipped ``notoes_collapse5pc`` topology
    ``coarse-369``  369       anny's shipped ``notoes_collapse3pc`` topology
    ==============  ========  =================================================================

Surfaces no scan has are removed from the full template (``faust`` and ``full``): the inside of the mouth
(a pocket 4 cm deep behind the lips) and the eye sockets behind the eyeballs, anny's texture regions
``mouth_cavity`` and ``eye_cavity.L/R``, are cut out and their openings (the lips, the eyelids) closed by
triangles between their two sides, with no new vertex; then interior components (eyeballs, tongue) are
removed by keeping the largest connected component. The kept vertices are renumbered in their template
order, the same way for every body. anny's coarse topologies carry no such regions and stay as shipped.

Parts (labels 0-7, in :data:`zernet.data.segmentation.HUMAN_PART_NAMES` order, left and right merged):
a vertex's part is the part whose bones carry the largest sum of its skinning weights.

    ==========  =============================================================================
    part        bones
    ==========  =============================================================================
    head        neck01-03, head, eye.L/R
    torso       root, pelvis.L/R, spine01-05, clavicle.L/R, shoulder01.L/R
    upper arm   upperarm01-02.L/R
    lower arm   lowerarm01-02.L/R
    hand        wrist.L/R, metacarpal*, finger*
    upper leg   upperleg01-02.L/R
    lower leg   lowerleg01-02.L/R
    foot        foot.L/R, toe*
    ==========  =============================================================================

Phenotypes, drawn uniformly: gender 0-1 (male-female), age 0.5-0.95 (adults; anny's 2/3 is "young",
1 "old"), muscle 0.1-0.9, weight 0.1-0.9, height 0.1-0.9, proportions 0.2-0.8; with poses ``wide``, muscle
and weight 0-1 (the model's limits: the thinnest, heaviest and most muscular bodies).

Poses (``poses=``): ``rest`` (anny's A-pose), ``varied`` (each joint rotation drawn uniformly in the
ranges below, left and right independently), ``mild`` (the same ranges halved), ``wide`` (the poses
people take in scans: each arm a style, overhead, crossed, behind the back, forward or down, the legs a
style, standing, stepping, bent (squats, sitting) or one-leg, each style with its own ranges;
:mod:`zernet.data.bodies.pose` and ``docs/BODIES.md`` hold them). Directions are in
anny's frame: forward is -y, up is +z, the body's left is +x (written bodies are then turned to FAUST's
frame: y up, facing +z). A rotation "toward D" turns the bone so that its
far end moves toward direction D; the ranges keep limbs off the body for every phenotype above.

    ===================  =====================  ==================================  =============
    joint group          bones                  rotation                            range (deg)
    ===================  =====================  ==================================  =============
    spine bend           spine03, spine01       about x (positive: bend forward)    -8 .. +15
    spine side bend      spine03, spine01       about y                             -8 .. +8
    spine twist          spine03                about z                             -20 .. +20
    head nod             neck01                 about x (positive: chin down)       -10 .. +20
    head turn            head                   about z                             -35 .. +35
    shoulder raise       upperarm01.L/R         toward up (negative: arm lowered)   -10 .. +45
    shoulder swing       upperarm01.L/R         toward forward (negative: back)     -25 .. +40
    elbow                lowerarm01.L/R         toward forward (flexion)            0 .. +75
    wrist                wrist.L/R              toward forward                      -25 .. +25
    hip swing            upperleg01.L/R         toward forward (negative: back)     -15 .. +50
    hip spread           upperleg01.L/R         toward the body's side (outward)    -3 .. +20
    knee                 lowerleg01.L/R         toward back (flexion)               0 .. +80
    ankle                foot.L/R               about x                             -15 .. +15
    ===================  =====================  ==================================  =============

Train and test bodies: body ``i`` of split ``s`` is drawn from its own random stream
``numpy.random.SeedSequence([seed, s, i])`` (s = 0 for train, 1 for test), so the test bodies' phenotypes
and poses are independent draws from a stream the training bodies never use (none is shared), and body i
does not change with ``count``.

Cache: the topology of each name and every generated body are stored under ``<cache_dir>/bodies/``, keyed
by the generator version, the anny version, the topology, the pose mode, the seed, the split and the
index, and written atomically. The anny model (whose first build takes a minute or more: it builds its
own cache and compiles kernels) is built only when something is missing from that cache.

This module is the public API; the work is done in ``pose`` (phenotype and pose draws, bone
rotations), ``topology`` (shared connectivity, part labels, the only anny import),
``generator`` (seeded, cached bodies), ``layout`` (files the loaders read) and ``forms``
(a body as scans come: remeshed, decimated, point clouds, one-sided; ground truth per vertex). The data kind
``"bodies"`` (:mod:`zernet.data.bodies.dataset`) trains on generated bodies without writing files.
"""

from __future__ import annotations

from zernet.data.bodies.dataset import load_bodies
from zernet.data.bodies.forms import (
    FORMS,
    BodyForm,
    closest_points,
    cloud_form,
    decimated_form,
    ground_truth,
    make_forms,
    noisy_cloud_form,
    nonmanifold_edge_count,
    partial_form,
    remeshed_form,
    resolve_forms,
)
from zernet.data.bodies.generator import GENERATOR_VERSION, Body, BodyGenerator, generate_bodies
from zernet.data.bodies.layout import FORM_SPLITS, BodiesLayout, FormsLayout, write_bodies, write_forms
from zernet.data.bodies.pose import POSE_MODES
from zernet.data.bodies.topology import MISSING_EXTRA_MESSAGE, PART_BONES, TOPOLOGIES, BodyTopology, part_of_bone

__all__ = [
    "GENERATOR_VERSION",
    "TOPOLOGIES",
    "POSE_MODES",
    "PART_BONES",
    "MISSING_EXTRA_MESSAGE",
    "Body",
    "BodyTopology",
    "BodiesLayout",
    "BodyGenerator",
    "part_of_bone",
    "generate_bodies",
    "write_bodies",
    "load_bodies",
    "FORMS",
    "FORM_SPLITS",
    "BodyForm",
    "FormsLayout",
    "make_forms",
    "resolve_forms",
    "remeshed_form",
    "decimated_form",
    "cloud_form",
    "noisy_cloud_form",
    "partial_form",
    "closest_points",
    "ground_truth",
    "nonmanifold_edge_count",
    "write_forms",
]
