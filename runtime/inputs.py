"""Checks of what a user names on the command line, made before anything starts (no device is opened, no
model loaded): device URLs, output paths, recordings. Each failure is a specific exception whose message
says what is wrong and what to do; the CLI prints it on one line and exits non-zero.
"""

from __future__ import annotations

from pathlib import Path

from drivers.errors import InvalidURL
from drivers.transport import TransportURL

MCAP_MAGIC = b"\x89MCAP0\r\n"


class InputError(ValueError):
    """A path or value given by the user cannot be used (the message names it and says why)."""


class NotARecording(InputError):
    """The file is not an MCAP recording (empty, or other bytes)."""


class CutRecording(InputError):
    """The MCAP recording ends without its footer: the recording process was killed or the disk filled."""


def check_device_url(url: str, role: str, *, optional: bool = False) -> None:
    """InvalidURL unless ``url`` names a tcp:// or serial:// link (``role``: 'laser' or 'base' for the
    message); ``optional``: '' and 'none' (no device) are accepted too."""
    if optional and url.strip().lower() in ("", "none"):
        return
    try:
        TransportURL.parse(url)
    except InvalidURL as exc:
        hint = f" ('none': no {role})" if optional else ""
        raise InvalidURL(f"{role} URL: {exc}{hint}") from None


def check_output_file(path: str | Path, what: str) -> Path:
    """The file ``path`` can be created: its directory exists and it is not a directory itself."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{what} {p} is a directory; give a file name, e.g. {p / 'run.mcap'}")
    if not p.parent.is_dir():
        raise InputError(f"{what} {p}: directory {p.parent} does not exist (create it first: mkdir -p {p.parent})")
    return p


def check_input_file(path: str | Path, what: str) -> Path:
    """``path`` exists and is a regular file."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} {p}: no such file")
    if p.is_dir():
        raise InputError(f"{what} {p} is a directory, not a file")
    return p


def check_mcap(path: str | Path, *, allow_cut: bool = False) -> bool:
    """True if ``path`` is a complete MCAP file; False if it is cut short and ``allow_cut``.

    NotARecording for an empty file or one that does not start like an MCAP file; CutRecording (unless
    ``allow_cut``) for one without the closing magic (no footer, no index), with the command that repairs it.
    """
    p = check_input_file(path, "recording")
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        if size == 0:
            raise NotARecording(f"{p}: empty file, not a recording")
        if head != MCAP_MAGIC:
            raise NotARecording(f"{p}: not an MCAP recording (it starts with {head[:8]!r}, not the MCAP magic)")
        f.seek(max(0, size - len(MCAP_MAGIC)))
        complete = size >= 2 * len(MCAP_MAGIC) and f.read() == MCAP_MAGIC
    if not complete and not allow_cut:
        raise CutRecording(f"{p}: the recording is cut short (no MCAP footer: the recording process was killed "
                           f"or the disk filled). Repair it with `glassmap recover {p} {p.with_suffix('')}"
                           f"-fixed.mcap` and replay the repaired file")
    return complete


def recover_recording(src: str | Path, dst: str | Path):
    """``runtime.recorder.recover_mcap`` with its inputs checked: ``src`` an MCAP file (complete or cut),
    ``dst`` a new file in an existing directory. The result is written beside ``dst`` and renamed into place
    only when it holds at least one message, so a failed repair leaves nothing half written."""
    from runtime.recorder import recover_mcap

    src_p = check_input_file(src, "recording")
    check_mcap(src_p, allow_cut=True)
    dst_p = check_output_file(dst, "output")
    if dst_p.exists() and dst_p.resolve() == src_p.resolve():
        raise InputError(f"{dst_p}: the repaired file must not overwrite the recording; give another name")
    tmp = dst_p.with_name(dst_p.name + ".part")
    try:
        rep = recover_mcap(src_p, tmp)
        if rep.messages == 0:
            raise InputError(f"{src_p}: no complete message to recover (the recording was cut before its "
                             "first chunk was written); nothing written")
        tmp.replace(dst_p)
    finally:
        tmp.unlink(missing_ok=True)
    return rep


__all__ = ["CutRecording", "InputError", "NotARecording", "check_device_url", "check_input_file", "check_mcap",
           "check_output_file", "recover_recording"]
