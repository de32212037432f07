"""What a long run has kept on disk so far, for the one line Ctrl-C prints (`hexjax.cli`). Resumable runs (the
sweeps' partial files, the tuner's checkpoints) say what they kept and how to resume after each piece."""

_KEPT = {"text": ""}


def keep(text: str) -> None:
    """Say what an interrupted run leaves behind and how to resume it."""
    _KEPT["text"] = text


def kept() -> str:
    return _KEPT["text"]
