"""A progress bar for the command line's long stages (generation, replays, builds)."""

from __future__ import annotations


class Progress:
    """A progress callback with a tqdm bar that opens on its first call (after the inputs are
    checked: a refused command prints no empty bar) and closes when ``total`` is reached (before
    the log lines that follow) or when its ``with`` block ends, however it ends."""

    def __init__(self, total: int, desc: str, unit: str = "gait") -> None:
        self.total, self.desc, self.unit = total, desc, unit
        self.bar = None

    @property
    def n(self) -> int:
        """Steps done so far."""
        return self.bar.n if self.bar is not None else 0

    def __call__(self, k: int) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(total=self.total, unit=self.unit, desc=self.desc)
        self.bar.update(k)
        if self.bar.n >= self.bar.total:
            self.bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
