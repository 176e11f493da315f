"""ICT-FaceKit blendshape names to Apple ARKit's 52 ``ARFaceAnchor.BlendShapeLocation`` names.

ICT-FaceKit names its shapes as ARKit does with ``_L``/``_R`` for ``Left``/``Right``, plus a few
of its own. ``--naming arkit`` renames every shape of ``ICT_TO_ARKIT``; ICT-FaceKit splits two
of ARKit's symmetric shapes in halves (``browInnerUp_L``/``_R``, ``cheekPuff_L``/``_R``): those
halves keep their names and ARKit's whole shape is added as their sum (``COMBINED``: blendshape
deltas add, so the sum is exact). Shapes with no ARKit name (``cheekRaiser_L``/``_R``,
``PupilDilate_L``/``_R``, any other name) keep theirs. ARKit's ``tongueOut`` has no ICT-FaceKit
shape (ICT-FaceKit's expression blendshapes move no tongue). With every ICT-FaceKit expression
trained, the rig has 51 of ARKit's 52 names.

``only_mapped`` (``fwk apply --only-mapped``): exactly the shapes with an ARKit name, in Apple's
order; the halves and the shapes with no ARKit name are left out.

Left and right: ARKit's are the face's own (Apple: "the eyeBlinkRight coefficient refers to the
face's right eye"), not the viewer's. ICT-FaceKit's ``_L``/``_R`` are the same: its head looks
along +z with y up, and ``eyeBlink_L`` closes the eye at +x, the face's own left. The renaming is
a renaming: ``_L`` becomes ``Left`` and no shape is mirrored.
"""
from __future__ import annotations

import numpy as np

from ..errors import FwkError

#: Apple ARKit's 52 blendshape names (ARFaceAnchor.BlendShapeLocation), in Apple's order
ARKIT_NAMES = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
    "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
    "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)

#: ICT-FaceKit name -> ARKit name (one to one)
ICT_TO_ARKIT = {
    "eyeBlink_L": "eyeBlinkLeft", "eyeLookDown_L": "eyeLookDownLeft", "eyeLookIn_L": "eyeLookInLeft",
    "eyeLookOut_L": "eyeLookOutLeft", "eyeLookUp_L": "eyeLookUpLeft", "eyeSquint_L": "eyeSquintLeft",
    "eyeWide_L": "eyeWideLeft", "eyeBlink_R": "eyeBlinkRight", "eyeLookDown_R": "eyeLookDownRight",
    "eyeLookIn_R": "eyeLookInRight", "eyeLookOut_R": "eyeLookOutRight", "eyeLookUp_R": "eyeLookUpRight",
    "eyeSquint_R": "eyeSquintRight", "eyeWide_R": "eyeWideRight", "jawForward": "jawForward", "jawLeft": "jawLeft",
    "jawRight": "jawRight", "jawOpen": "jawOpen", "mouthClose": "mouthClose", "mouthFunnel": "mouthFunnel",
    "mouthPucker": "mouthPucker", "mouthLeft": "mouthLeft", "mouthRight": "mouthRight",
    "mouthSmile_L": "mouthSmileLeft", "mouthSmile_R": "mouthSmileRight", "mouthFrown_L": "mouthFrownLeft",
    "mouthFrown_R": "mouthFrownRight", "mouthDimple_L": "mouthDimpleLeft", "mouthDimple_R": "mouthDimpleRight",
    "mouthStretch_L": "mouthStretchLeft", "mouthStretch_R": "mouthStretchRight", "mouthRollLower": "mouthRollLower",
    "mouthRollUpper": "mouthRollUpper", "mouthShrugLower": "mouthShrugLower", "mouthShrugUpper": "mouthShrugUpper",
    "mouthPress_L": "mouthPressLeft", "mouthPress_R": "mouthPressRight", "mouthLowerDown_L": "mouthLowerDownLeft",
    "mouthLowerDown_R": "mouthLowerDownRight", "mouthUpperUp_L": "mouthUpperUpLeft",
    "mouthUpperUp_R": "mouthUpperUpRight", "browDown_L": "browDownLeft", "browDown_R": "browDownRight",
    "browOuterUp_L": "browOuterUpLeft", "browOuterUp_R": "browOuterUpRight", "cheekSquint_L": "cheekSquintLeft",
    "cheekSquint_R": "cheekSquintRight", "noseSneer_L": "noseSneerLeft", "noseSneer_R": "noseSneerRight",
}

#: ARKit's symmetric shapes that ICT-FaceKit splits in halves: ARKit name -> (left, right)
COMBINED = {"browInnerUp": ("browInnerUp_L", "browInnerUp_R"), "cheekPuff": ("cheekPuff_L", "cheekPuff_R")}

NAMINGS = ("source", "arkit")
#: the namings that map names to a standard set: naming -> the standard's names, in its order
MAPPED = {"arkit": ARKIT_NAMES}
#: the standard's name in messages
STANDARD = {"arkit": "ARKit"}


def check_only_mapped(naming: str) -> None:
    """The one-line error for ``--only-mapped`` under a naming that maps no names."""
    if naming not in MAPPED:
        raise FwkError(f"--only-mapped keeps the shapes a naming maps: use it with --naming "
                       f"{' or '.join(MAPPED)} (--naming {naming} maps no names)")


def rename(shapes: dict[str, np.ndarray], neutral: np.ndarray, naming: str = "source",
           only_mapped: bool = False) -> dict[str, np.ndarray]:
    """The shapes (name -> positions) under ``naming``: ``source`` keeps the names; ``arkit``
    renames ICT-FaceKit's names to ARKit's and adds ARKit's symmetric shapes whose halves are
    present (their deltas from ``neutral`` summed). Order: the input's, the added shapes last.
    ``only_mapped``: only the shapes named by the naming's standard (``MAPPED``), in its order
    (a one-line error when there are none, or under ``source``)."""
    if naming not in NAMINGS:
        raise FwkError(f"--naming {naming}: unknown naming (namings: {', '.join(NAMINGS)})")
    if only_mapped:
        check_only_mapped(naming)
    if naming == "source":
        return dict(shapes)
    out = {}
    for name, V in shapes.items():
        new = ICT_TO_ARKIT.get(name, name)
        if new in out or (new != name and new in shapes):
            raise FwkError(f"--naming arkit: two shapes would be called {new} ({name} and another); "
                           "rename one of the run's expressions")
        out[new] = V
    for whole, (left, right) in COMBINED.items():
        if left in shapes and right in shapes and whole not in out:
            out[whole] = shapes[left] + shapes[right] - neutral
    if only_mapped:
        kept = {n: out[n] for n in MAPPED[naming] if n in out}
        if not kept:
            listed = ", ".join(list(shapes)[:6]) + (", ..." if len(shapes) > 6 else "")
            raise FwkError(f"--only-mapped: no shape has an {STANDARD[naming]} name (the shapes: {listed}); leave "
                           "--only-mapped out to keep them under their own names")
        return kept
    return out


def mapped_sources(names: list[str], naming: str) -> list[str]:
    """The names (in order) whose shapes ``rename(..., only_mapped=True)`` keeps under
    ``naming``: renamed into the standard, or a half of one of its symmetric shapes (``COMBINED``)
    that is not itself among the names; what ``fwk rig`` predicts (ICT-FaceKit under arkit: 53 of
    57, without cheekRaiser_L/R and PupilDilate_L/R)."""
    check_only_mapped(naming)
    std = set(MAPPED[naming])
    halves = {h for whole, pair in COMBINED.items() if whole in std and whole not in names for h in pair}
    return [n for n in names if ICT_TO_ARKIT.get(n, n) in std or n in halves]


def only_mapped_note(source: list[str], kept: list[str], naming: str) -> str:
    """One line on what ``--only-mapped`` kept and left out: ``source``, the run's names;
    ``kept``, the names written."""
    std, label = MAPPED[naming], STANDARD[naming]
    absent = [n for n in std if n not in kept]
    dropped = [n for n in source if ICT_TO_ARKIT.get(n, n) not in kept]
    text = f"--only-mapped: {len(kept)} of {label}'s {len(std)} shapes"
    if absent:
        text += f" (none for {', '.join(absent)})" if len(absent) <= 5 else f" (none for {len(absent)} of them)"
    if dropped:
        text += f"; left out, with no {label} name: {', '.join(dropped)}"
    return text
