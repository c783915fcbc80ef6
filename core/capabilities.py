"""What a retargeter consumes, needs and offers: the vocabulary shared by the classes
(:mod:`faceretarget.retargeter`) and their manifests (:mod:`faceretarget.manifest`), a leaf
module so that neither imports the other for it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["RIG_PARTS", "SOURCE_EXTRAS", "SOURCE_KINDS", "Capabilities"]

#: Kinds of performance a retargeter can consume.
SOURCE_KINDS = ("markers", "mesh", "weights")
#: Rig parts (see :attr:`TargetRig.PARTS`) and source extras a retargeter can need.
RIG_PARTS = ("blendshapes", "layers", "landmarks", "feature_lines", "examples")
SOURCE_EXTRAS = (
    "source_landmarks",
    "source_examples",
    "source_feature_lines",
    "actor_layers",
    "source_rig",
)


@dataclass(frozen=True)
class Capabilities:
    """What a retargeter consumes, needs and offers.

    sources : source kinds accepted (any of ``SOURCE_KINDS``)
    needs : rig parts the target must have (``RIG_PARTS``) and source extras
        (``SOURCE_EXTRAS``); a tuple of alternatives ``("a", "b")`` inside means "a or b"
    outputs : "weights" (blendshape-based result) or "vertices"
    stream : offers ``stream(frames)``
    edit : offers ``edit(animation, ...)``
    same_topology : needs source and target meshes of one topology
    """

    sources: tuple[str, ...] = ("markers",)
    needs: tuple[str | tuple[str, ...], ...] = ()
    outputs: str = "vertices"
    stream: bool = False
    edit: bool = False
    same_topology: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {
            "sources": list(self.sources),
            "needs": [list(n) if isinstance(n, tuple) else n for n in self.needs],
            "outputs": self.outputs,
            "stream": self.stream,
            "edit": self.edit,
            "same_topology": self.same_topology,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Capabilities:
        return cls(
            sources=tuple(data.get("sources", ("markers",))),
            needs=tuple(tuple(n) if isinstance(n, list) else n for n in data.get("needs", ())),
            outputs=data.get("outputs", "vertices"),
            stream=bool(data.get("stream", False)),
            edit=bool(data.get("edit", False)),
            same_topology=bool(data.get("same_topology", False)),
        )
