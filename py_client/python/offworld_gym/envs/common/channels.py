"""Camera channels of an observation (the original's ``Channels``)."""

from enum import IntEnum


class Channels(IntEnum):
    """Which camera channels an observation carries (the native layer reads
    the value: keep it in step with ``convert::channels`` in
    ``py_client/src/convert.rs``)."""

    DEPTH_ONLY = 1
    RGB_ONLY = 2
    RGBD = 3

    @property
    def count(self) -> int:
        """Channels per pixel."""
        return {Channels.DEPTH_ONLY: 1, Channels.RGB_ONLY: 3, Channels.RGBD: 4}[self]
