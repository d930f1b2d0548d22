"""The seed-to-key algorithm: the contract's HMAC with a key file, or the OEM's, named one way
everywhere a key is needed (``flash``, ``ecu restore``, ``run``, ``station`` and the station
settings' ``key_algo``).

An OEM's algorithm is named as an installed entry point of the group ``eol_cal.seed_to_key``
(``key_algo = "oem-eps"``: a plug-in package the OEM ships) or as ``MODULE:FUNC`` (a module on
the Python path). Either way it is called as ``FUNC(seed: bytes, secret: bytes | None) -> key
bytes`` (``secret``: the key file's 16 bytes when one is given), and it is tried on a made-up
seed when it is loaded, so a wrong one is refused before the dyno moves or a session opens;
whatever it does wrong then or later is one line naming its file, never a traceback in the
middle of a flash. It runs in a child process (:mod:`eol_cal.ecu.keychild`): an algorithm that
exits, raises ``BaseException``, hangs or returns 200 MB cannot decide the command's exit code
or the ECU's fate; the command refuses (exit 2) within a bound and nothing is flashed.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import entry_points

from eol_cal.ecu.client import hmac_seed_to_key, load_key_file
from eol_cal.ecu.keychild import ContainedKey
from eol_cal.errors import InputError

SeedToKey = Callable[[bytes], bytes]

#: the entry-point group an OEM's plug-in registers its seed-to-key function in
ENTRY_POINT_GROUP = "eol_cal.seed_to_key"
#: the seed an algorithm is tried on when it is loaded (the contract's seeds are 4 bytes)
SEED_TRIAL = b"\x12\x34\x56\x78"


def _resolve(spec: str, field: str) -> tuple[str, str, str]:
    """(module, function, spec as shown) of ``spec``: an entry point's target (read from the
    installed metadata; nothing of the plug-in runs here), or ``MODULE:FUNC``."""
    module_name, colon, func_name = spec.partition(":")
    if not colon:
        found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == spec]
        if not found:
            names = sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
            installed = f"installed: {', '.join(names)}" if names else "none installed"
            raise InputError(None, field, f"{spec!r}: no entry point of that name in group {ENTRY_POINT_GROUP} "
                                          f"({installed}); or give MODULE:FUNC")
        module_name, _, func_name = found[0].value.partition(":")
        spec = f"{spec} ({found[0].value})"
    if not module_name or not func_name:
        raise InputError(None, field, f"{spec!r}: expected MODULE:FUNC or an entry point name")
    return module_name, func_name, spec


def oem_seed_to_key(spec: str, secret: bytes | None, field: str = "key-algo") -> SeedToKey:
    """The seed-to-key function ``spec`` names (see the module docstring), loaded in a child
    process of its own (:class:`eol_cal.ecu.keychild.ContainedKey`) and tried once.

    Raises
    ------
    InputError
        It cannot be found or loaded, it fails on the trial seed (raises anything, exits, hangs
        past :data:`eol_cal.ecu.keychild.KEY_TIMEOUT_S`), or returns no key bytes (text, an empty
        key, one over :data:`eol_cal.ecu.keychild.MAX_KEY_BYTES`); names the module's file (or the
        spec) and ``field``.
    """
    module_name, func_name, shown = _resolve(spec, field)
    seed_to_key = ContainedKey(module_name, func_name, shown, secret, field)
    seed_to_key(SEED_TRIAL)
    return seed_to_key


def seed_to_key_from(key_file: str | None, key_algo: str | None, *, file_field: str = "key-file",
                     algo_field: str = "key-algo") -> SeedToKey:
    """The algorithm a command uses: ``key_algo`` (with the key file's secret, if one is given),
    else the contract's HMAC with the key file's secret.

    Raises
    ------
    InputError
        Neither is given, the key file is unreadable or not 16 bytes of hex, or the algorithm is
        refused (:func:`oem_seed_to_key`).
    """
    secret = load_key_file(key_file) if key_file else None
    if key_algo:
        return oem_seed_to_key(key_algo, secret, algo_field)
    if secret is None:
        said = {f: f"--{f}" if "-" in f else f for f in (file_field, algo_field)}  # an option, or a settings key
        raise InputError(None, file_field, f"security access needs the ECU's secret: give {said[file_field]} (16 "
                                           f"bytes, hex), or the OEM's algorithm with {said[algo_field]}")
    return hmac_seed_to_key(secret)
