"""The archive of what a run wrote into the ECU: every block, byte for byte as it went in.

The flash gives a block the ECU's next sequence and the CRC over it
(:func:`eol_cal.ecu.sequence.flash_block`), so the block a run builds is not the block the ECU
holds. :func:`flash_archived` flashes a block and keeps the image the flash wrote (sequence and
CRC set) in the run's directory, atomically, with its SHA-256 in the record
(:class:`~eol_cal.records.record.FlashedBlock`): ``eol-cal block show`` of the file says what
``eol-cal ecu info`` says after the run, and the file equals the bank's bytes. A flash that fails
after the CRC went out (the ECU may boot the new block at its next reset) archives the image all
the same, as not confirmed.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from eol_cal.infra.atomic import atomic_path
from eol_cal.ecu.client import flash_block
from eol_cal.firmware import block as B
from eol_cal.firmware.mech import mech_enabled
from eol_cal.firmware.options import honoured_options, options_label
from eol_cal.records.record import FlashedBlock, PreviousBlock

if TYPE_CHECKING:
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.domain.motor_params import MotorParams


def write_archive(path: Path, image: bytes) -> str:
    """Write ``image`` to ``path`` atomically; returns its SHA-256 (hex)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(image)
    return hashlib.sha256(image).hexdigest()


def block_fields(image: bytes) -> dict[str, Any]:
    """What the record says of a block's content: flags by name, the estimator options they
    select, table length, lead (s), current limit (A), layout, whether its mechanical
    compensation is on (layout 2)."""
    blk = B.unpack(image, "<flashed block>")
    assert blk.layout_version is not None  # a ParamBlock's layout is never None once made (__post_init__)
    mech = None if blk.mech is None else ("on" if mech_enabled(blk.flags, blk.layout_version, blk.mech) else "off")
    return {"flags": B.flag_names(blk.flags), "estimator": options_label(honoured_options(blk.flags)),
            "table_len": int(blk.table_len), "lead_s": float(blk.lead_s), "iqc_limit": float(blk.iqc_limit),
            "layout_version": int(blk.layout_version), "mech": mech}


def flashed_block(role: str, path: Path, report: FlashReport) -> FlashedBlock:
    """The record of a completed flash whose image was archived at ``path``."""
    image = report.image
    prev = report.previous
    return FlashedBlock(role=role, path=str(path), sha256=write_archive(path, image), bytes=len(image),
                        bank=report.bank, sequence=report.sequence, crc32=f"{report.crc32:08x}", verified=report.verified,
                        confirmed=True, previous=PreviousBlock(prev.bank if prev.has_bank else None, prev.sequence),
                        seconds=round(report.seconds, 4), transfer_blocks=report.transfer_blocks,
                        retries=report.retries, **block_fields(image))


def flash_archived(open_bus: Callable[[], Any], data: bytes, *, role: str, path: Path,
                   seed_to_key: Callable[[bytes], bytes], timing: Any, motor: MotorParams, source: str,
                   progress: Callable[[str], None] | None = None,
                   before_commit: Callable[[], None] | None = None,
                   read_back: bool = True) -> tuple[FlashReport, FlashedBlock]:
    """Flash ``data`` on a bus of its own and archive the image as flashed at ``path``
    (``before_commit``: :func:`eol_cal.ecu.client.flash_block`'s; ``read_back``: its ``verify``,
    the block read back before its CRC is written).

    An exception raised after the block's CRC went out carries ``flashed_block``: the archived
    image's record, ``confirmed`` False (the ECU boots it at its next reset, or may).
    """
    bus = open_bus()
    try:
        return archived(role, path, lambda: flash_block(bus, data, seed_to_key=seed_to_key, verify=read_back,
                                                        source=source, timing=timing, motor=motor, progress=progress,
                                                        before_commit=before_commit), read_back=read_back)
    finally:
        bus.shutdown()


def archived(role: str, path: Path, flash: Callable[[], FlashReport],
             read_back: bool = True) -> tuple[FlashReport, FlashedBlock]:
    """Run ``flash`` and archive the image it wrote at ``path`` (:func:`flash_archived`); an
    exception after the CRC went out carries ``flashed_block``, not confirmed (``verified``: the
    flash read the block back, ``read_back``, and the CRC goes out only after that)."""
    try:
        report = flash()
    except BaseException as exc:
        image = getattr(exc, "flashed_image", None)
        boots = getattr(exc, "ecu_boots", None) or {}
        if image:
            exc.flashed_block = FlashedBlock(  # type: ignore[attr-defined]
                role=role, path=str(path), sha256=write_archive(path, image), bytes=len(image),
                bank=boots.get("bank"), sequence=boots.get("sequence"),
                crc32=f"{B.check(image).crc_stored or 0:08x}", verified=read_back, confirmed=False, **block_fields(image))
        raise
    return report, flashed_block(role, path, report)


def keep_flashed(blocks: list[FlashedBlock], flash: Callable[[], tuple[FlashReport, FlashedBlock]]) -> FlashReport:
    """Run ``flash`` (:func:`flash_archived`, or the flash opened ahead) and append its block to the
    run's ``blocks``; a flash that failed after the block's CRC went out appends the block its
    exception carries (``flashed_block``: the ECU boots it, or may) and raises on."""
    try:
        report, done = flash()
    except BaseException as exc:
        flashed = getattr(exc, "flashed_block", None)
        if flashed is not None:
            blocks.append(flashed)
        raise
    blocks.append(done)
    return report
