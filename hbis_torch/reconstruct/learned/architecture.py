"""The network's architecture as one small record, which travels with the model.

Training builds the network from an :class:`Architecture` (:func:`hbis_torch.reconstruct.learned.network.build_net`),
checkpoints store it (:meth:`Architecture.as_dict`), the export writes it into the ONNX file's
``model_config`` metadata (:meth:`Architecture.to_metadata`), and the runtime reads it back
(:meth:`Architecture.from_metadata`) to size the tiles' halo (:attr:`Architecture.halo`). Changing
the network's size or kind is thus one record: nothing else names ``width`` or ``blocks``.

This module needs no torch: the run-time side of the learned method imports it.
"""

from __future__ import annotations

import dataclasses
import json

from hbis_torch.checks import check_h
from hbis_torch.errors import HbisInputError

# The residual body's blocks: "plain" is the shipped design (conv 3x3 -> ReLU -> conv 3x3);
# "ir" is MobileNetV2's inverted residual (conv 1x1 to IR_EXPAND x width -> ReLU -> depthwise
# conv 3x3 -> ReLU -> conv 1x1 back), about half a plain block's multiply-adds at equal width.
KINDS = ("plain", "ir")
IR_EXPAND = 4
# Receptive-field radius (LR pixels) each block adds: two 3x3 convolutions, or one.
_BLOCK_RADIUS = {"plain": 2, "ir": 1}


@dataclasses.dataclass(frozen=True)
class Architecture:
    """The network's constructor arguments.

    Parameters
    ----------
    h : int
        Resolution improvement factor (>= 2): h^2 + 1 input channels, h^2 output channels.
    width : int
        Feature channels of the residual body.
    blocks : int
        Number of residual blocks.
    kind : {"plain", "ir"}
        The body's blocks (:data:`KINDS`).
    """

    h: int
    width: int = 32
    blocks: int = 4
    kind: str = "plain"

    def __post_init__(self) -> None:
        check_h(self.h, minimum=2)
        if self.kind not in KINDS:
            raise HbisInputError(f"unknown network kind {self.kind!r} (choose from {', '.join(KINDS)})")
        if int(self.width) < 1 or int(self.blocks) < 0:
            raise HbisInputError(f"width must be >= 1 and blocks >= 0, got {self.width} and {self.blocks}")
        for name in ("h", "width", "blocks"):
            object.__setattr__(self, name, int(getattr(self, name)))

    @property
    def halo(self) -> int:
        """Receptive-field radius in LR pixels, plus one: head (1) + the blocks + tail (1) + 1.
        A tile needs this much context on each side for its output to equal the whole image's."""
        return 1 + _BLOCK_RADIUS[self.kind] * self.blocks + 1 + 1

    def as_dict(self) -> dict:
        """The fields by name (what a training checkpoint stores as ``model_config``)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, config: dict) -> Architecture:
        """From :meth:`as_dict`; a dict without ``kind`` (models made before it existed) is plain."""
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in config.items() if k in fields})

    def to_metadata(self) -> dict[str, str]:
        """The ONNX ``metadata_props`` entries the architecture owns: ``model_config`` (JSON)."""
        return {"model_config": json.dumps(self.as_dict())}

    @classmethod
    def from_metadata(cls, metadata: dict) -> Architecture:
        """From a model's ``metadata_props`` (:func:`~hbis_torch.reconstruct.learned.runtime.read_model_metadata`).

        ``model_config`` gives the fields; a missing entry takes its default (the shipped
        design's), and ``h`` comes from the metadata's own ``h`` where ``model_config`` lacks it.
        """
        config = json.loads(metadata.get("model_config") or "{}")
        config.setdefault("h", int(metadata["h"]))
        return cls.from_dict(config)
