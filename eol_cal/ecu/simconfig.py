"""What the simulated ECU is (:class:`SimConfig`) and the faults it injects (:class:`Faults`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from eol_cal.ecu import protocol as P
from eol_cal.ecu.transport import IsoTpTiming
from eol_cal.firmware import block as B

STEPS = ("session", "security", "read_did", "erase", "download", "transfer", "transfer_exit",
         "check", "read_memory", "reset", "tester_present")
"""Names of the steps a power loss can be placed at (contract section 3 order)."""


@dataclass
class Faults:
    """Faults the simulator injects.

    Attributes
    ----------
    power_loss_step : str or None
        Power fails when a request of this step (one of :data:`STEPS`) arrives. For
        ``erase`` the sector is left with arbitrary words; for ``transfer`` programming is cut
        in the middle of the first TransferData block; other steps change no flash.
    power_loss_occurrence : int
        Which request of ``power_loss_step`` fails (1 = the first; the flash reads DIDs
        before the erase and again after the reset).
    power_loss_byte : int or None
        Power fails while programming this byte offset of the download.
    corrupt_byte : int or None
        A worn flash cell: this byte offset of the download is stored with bit 0 cleared, so
        the check routine reports a CRC mismatch.
    drop_rate : float
        Probability that a frame the ECU sends or receives is lost.
    delay_rate, delay_s : float
        Probability that a frame the ECU sends is held ``delay_s`` seconds first.
    nrc : dict of int to int
        Request service ID -> NRC the ECU answers instead of serving it.
    wrong_block_counter : int or None
        The n-th TransferData request (1-based) is answered NRC 0x73.
    drop_response : dict of str to int or tuple of int
        Step (one of :data:`STEPS`) -> the n-th request(s) of it (1-based) are served but their
        answers are lost on the way back.
    slow_step : dict of str to float
        Step -> extra seconds every request of it takes (answered 0x78 meanwhile).
    stale_answers : bool
        A late duplicate at every step: before serving a request, the ECU sends its previous
        answer again (as an ECU does that answers a request the tester gave up on and repeated),
        so that it arrives while the tester waits for this request's answer. Not done where
        UDS lets no tester tell the two apart: the same service without an echo (two
        ReadMemoryByAddress of one size) or the very same answer again.
    seed : int
        Seed of every random choice (dropped frames, arbitrary words, seeds).
    """

    power_loss_step: str | None = None
    power_loss_occurrence: int = 1
    power_loss_byte: int | None = None
    corrupt_byte: int | None = None
    drop_rate: float = 0.0
    delay_rate: float = 0.0
    delay_s: float = 0.0
    nrc: dict[int, int] = field(default_factory=dict)
    wrong_block_counter: int | None = None
    drop_response: dict[str, int | tuple[int, ...]] = field(default_factory=dict)
    slow_step: dict[str, float] = field(default_factory=dict)
    stale_answers: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        for step in (self.power_loss_step, *self.drop_response, *self.slow_step):
            if step is not None and step not in STEPS:
                raise ValueError(f"step {step!r} not one of {STEPS}")


@dataclass(frozen=True)
class SimConfig:
    """What the simulated ECU is and how fast it runs.

    Attributes
    ----------
    serial : str
        Motor serial answered on DID F18C.
    sw_version : str
        DID F195.
    layouts : tuple of int
        Supported layout versions (DID FD00).
    secret : bytes
        16-byte security secret (the contract's development secret by default).
    s3_s, lockout_s, p2_s, p2_star_s : float
        Session timeout, security lock-out delay, announced P2 and P2*, s.
    erase_s : float
        Sector erase time, s (answered with NRC 0x78 first).
    max_block_length : int
        maxNumberOfBlockLength of the RequestDownload response: bytes of one TransferData
        request, service ID and counter included.
    isotp_timing : IsoTpTiming
    bitrate : int or None
        The CAN bit rate (bit/s) the simulator's bus is paced to, both directions
        (:class:`~eol_cal.ecu.wire.PacedBus`); None: frames as fast as the virtual bus carries them.
    """

    serial: str = "SIM-0001"
    sw_version: str = "eol-cal-sim 1"
    layouts: tuple[int, ...] = B.SUPPORTED_LAYOUTS
    secret: bytes = P.DEV_SECRET
    s3_s: float = P.S3_S
    lockout_s: float = P.LOCKOUT_S
    p2_s: float = P.P2_S
    p2_star_s: float = P.P2_STAR_S
    erase_s: float = 0.05
    max_block_length: int = 4094
    isotp_timing: IsoTpTiming = IsoTpTiming()
    bitrate: int | None = None
