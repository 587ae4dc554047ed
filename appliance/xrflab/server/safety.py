"""Putting a real ico board's outputs in a safe state when its loop process is gone.

The FPGA's RESET command zeroes all PWM outputs. The loop normally owns /dev/spidev0.0; once it
has died nobody does, so the appliance sends the frame itself through plain Linux spidev (no EVL
needed: this is not on a real-time path, it is a one-off after the fact).
"""

from __future__ import annotations

import fcntl
import os
import struct

FRAME_BYTES = 12
OP_RESET = 2
SPI_SPEED_HZ = 31_000_000

# <linux/spi/spidev.h> ioctls: _IOW('k', nr, type) = (1 << 30) | (sizeof << 16) | ('k' << 8) | nr.
_SPI_IOC_WR_MODE = 0x40016B01
_SPI_IOC_WR_BITS_PER_WORD = 0x40016B03
_SPI_IOC_WR_MAX_SPEED_HZ = 0x40046B04


def _reverse_bits(byte: int) -> int:
    # The ico board is LSB-first on the wire; spidev shifts MSB-first, so every byte is mirrored
    # (XRF2 does the same in software).
    return int(f"{byte:08b}"[::-1], 2)


def reset_frame() -> bytes:
    """The 12-byte RESET frame [2, 0, ...] as it goes to spidev (bit-reversed)."""
    frame = bytes([OP_RESET] + [0] * (FRAME_BYTES - 1))
    return bytes(_reverse_bits(b) for b in frame)


def fpga_reset(device: str = "/dev/spidev0.0") -> bool:
    """Send RESET to the ico board; False when there is no such device (nothing to reset)."""
    if not os.path.exists(device):
        return False
    fd = os.open(device, os.O_RDWR)
    try:
        fcntl.ioctl(fd, _SPI_IOC_WR_MODE, struct.pack("B", 0))
        fcntl.ioctl(fd, _SPI_IOC_WR_BITS_PER_WORD, struct.pack("B", 8))
        fcntl.ioctl(fd, _SPI_IOC_WR_MAX_SPEED_HZ, struct.pack("I", SPI_SPEED_HZ))
        # A plain write() is one half-duplex transfer: all RESET needs (the reply is not used).
        os.write(fd, reset_frame())
    finally:
        os.close(fd)
    return True
