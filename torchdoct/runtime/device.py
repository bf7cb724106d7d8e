"""The ``--device`` check shared by every command that computes with torch (simulate, render, maps)."""

from __future__ import annotations

__all__ = ["available_devices", "check_device"]

#: Device types the computations run on (each with a ``torch.<type>``/``torch.backends.<type>`` backend).
_COMPUTE_TYPES = ("cpu", "cuda", "mps", "xpu")


def _backend(kind: str):
    import torch

    return torch.backends.mps if kind == "mps" else getattr(torch, kind, None)


def available_devices() -> list[str]:
    """The devices this machine and torch build can compute on: ``cpu``, then ``cuda:i``, ``mps``, ``xpu:i``."""
    out = ["cpu"]
    for kind in _COMPUTE_TYPES[1:]:
        backend = _backend(kind)
        if backend is None or not backend.is_available():
            continue
        count = getattr(backend, "device_count", lambda: 1)()
        out += [kind] if kind == "mps" else [f"{kind}:{i}" for i in range(count)]
    return out


def check_device(device: str | None, what: str = "--device") -> str | None:
    """``device`` unchanged if torch can compute on it here, else a ``ValueError`` naming the devices
    that exist and how to choose one. ``None`` (the default device, cpu) passes."""
    if device is None:
        return None
    import torch

    have = available_devices()
    fix = f"devices here: {', '.join(have)}. Fix: pass one of them (--device cpu, or leave --device out for cpu)"
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"{what} {device!r} is not a torch device name (cpu, cuda, cuda:N, mps, xpu); {fix}") from None
    if dev.type not in _COMPUTE_TYPES:
        raise ValueError(f"{what} {device!r}: torchdoct computes on cpu, cuda, mps or xpu, not {dev.type}; {fix}")
    if dev.type == "cpu":
        return device
    backend = _backend(dev.type)
    if backend is None or not backend.is_available():
        if dev.type == "cuda" and torch.version.cuda is None:
            reason = f"this torch build ({torch.__version__}) has no CUDA support"
            fix += "; for a GPU install a CUDA build of torch (https://pytorch.org/get-started/locally/)"
        else:
            kind = "MPS" if dev.type == "mps" else dev.type.upper()
            reason = f"no {kind} device is available to torch {torch.__version__}"
        raise ValueError(f"{what} {device!r}: {reason}; {fix}")
    if dev.index is not None and dev.type != "mps" and dev.index >= backend.device_count():
        raise ValueError(
            f"{what} {device!r}: there are {backend.device_count()} {dev.type.upper()} devices "
            f"(0-{backend.device_count() - 1}); {fix}"
        )
    return device
