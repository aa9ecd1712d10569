"""Everything that touches a wire: the MPU-9250/AK8963 driver, fake buses, serial frames,
and sample sources that all yield :class:`SampleBlock`. Nothing here knows about fitting."""
from .sample import SampleBlock

__all__ = ["SampleBlock"]
