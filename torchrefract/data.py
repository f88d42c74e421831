"""Deprecated alias of :mod:`torchrefract.dataset` (the torch datasets moved to
``torchrefract.dataset.loaders`` in the redesign of issue #23)."""

import warnings

from torchrefract.dataset.loaders import (
                                          RefractDataset,
                                          RenderStream,
                                          collate,
                                          decode_exr,
                                          decode_wds,
)

warnings.warn("torchrefract.data is deprecated: import RefractDataset, RenderStream, ... "
              "from torchrefract.dataset", DeprecationWarning, stacklevel=2)

__all__ = ["RefractDataset", "RenderStream", "collate", "decode_exr", "decode_wds"]
