"""Two data roots in one training run: every window of the primary root once per epoch, topped up with windows of a
second root to a fixed share of the epoch.

What it is for: fine-tuning on a handful of labelled real scans (the primary root: 11 windows) while replaying
simulated drives (the mix root: hundreds of windows), so the model learns the real returns without forgetting
what the simulation taught it. Concatenating the two roots would drown the real windows (11 of 370); repeating them
by hand would fix the share only for one size of either root. Here the share is a number: `share` 0.5 puts as many
simulated windows into each epoch as there are real ones, in shuffled order (the trainer's sampler shuffles the
epoch's slots), so a batch of 4 holds two of each on average.

Which mix windows an epoch gets is a function of (seed, epoch, slot) only, like the augmentation
(rafd.data.dataset): an endless walk through seeded permutations of the mix root, each lap visiting every mix window
once, the epoch taking the next `per_epoch` steps of the walk. So a resumed run is exact, and over the epochs every
mix window is seen equally often.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from torch.utils.data import Dataset


class MixedWindows(Dataset):
    """Epoch slots 0..len(primary)-1 are the primary's windows; the next `per_epoch` slots are mix windows. Keys are
    (epoch, slot), as rafd.train.distributed.EpochSampler yields them; each dataset draws its own augmentation."""

    def __init__(self, primary: Any, mix: Any, share: float, seed: int = 0) -> None:
        if not 0.0 < share < 1.0:
            raise ValueError(f"the mix share must be in (0, 1), got {share}")
        if len(primary) == 0 or len(mix) == 0:
            raise ValueError("both the primary and the mix data need windows")
        self.primary, self.mix, self.share, self.seed = primary, mix, float(share), int(seed)
        # share = per_epoch / (len(primary) + per_epoch), rounded to whole windows (at least one)
        self.per_epoch = max(1, round(len(primary) * share / (1.0 - share)))

    def __len__(self) -> int:
        return len(self.primary) + self.per_epoch

    @property
    def sequences(self) -> list:
        """Both roots' sequences (what a window dataset exposes)."""
        return list(self.primary.sequences) + list(self.mix.sequences)

    def mix_index(self, epoch: int, slot: int) -> int:
        """The mix window that slot `slot` (0..per_epoch-1) of `epoch` holds."""
        step = int(epoch) * self.per_epoch + int(slot)  # position on the endless walk
        lap, position = divmod(step, len(self.mix))
        order = np.random.default_rng([self.seed, lap]).permutation(len(self.mix))
        return int(order[position])

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        epoch, index = key if isinstance(key, tuple) else (0, key)
        if not 0 <= index < len(self):
            raise IndexError(f"window {index} out of range ({len(self)} windows per epoch)")
        if index < len(self.primary):
            return self.primary[(epoch, index)]
        return self.mix[(epoch, self.mix_index(epoch, index - len(self.primary)))]
