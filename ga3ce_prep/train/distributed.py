"""Data-parallel training under torchrun (`torchrun --nproc-per-node N ... ga3ce-prep train ...`).

Every process builds the same model (same seed) and draws the same batches, the same global
batch of `batch_size` frames per step and its view noise; each takes a contiguous share of the
batch's rows (`Ranks.share`) and DistributedDataParallel averages the gradients (gloo on CPU, nccl
on CUDA, one GPU per process). Each rank's loss is scaled by its share of the rows times the
world size, so the averaged gradient is the global batch's mean gradient, as in one process; a
rank without rows (a last batch smaller than the world) runs one row at weight 0. Rank 0
validates and writes the run folder. Dropout masks are each rank's own draws (seeded by seed,
epoch and rank): with dropout 0 the loss curve is one process's to float tolerance.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Ranks:
    """This process's place in the job: rank of world (0 of 1 without torchrun), and its GPU."""

    rank: int = 0
    world: int = 1
    local: int = 0

    @classmethod
    def from_env(cls) -> Ranks:
        """The place torchrun gives this process (RANK, WORLD_SIZE, LOCAL_RANK); 0 of 1 without it."""
        env = os.environ
        return cls(int(env.get("RANK", "0")), int(env.get("WORLD_SIZE", "1")), int(env.get("LOCAL_RANK", "0")))

    def join(self, device: torch.device) -> bool:
        """Join torchrun's process group (gloo on CPU, nccl on CUDA) unless there is one process or
        the group exists; True when this call started it (then `leave` ends it)."""
        if self.world == 1:
            return False
        import torch.distributed as dist

        if dist.is_initialized():
            return False
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return True

    @property
    def main(self) -> bool:
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This rank's rows of a global batch of n: contiguous, sizes differ by at most one."""
        q, r = divmod(n, self.world)
        start = self.rank * q + min(self.rank, r)
        return slice(start, start + q + (self.rank < r))

    def wrap(self, model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
        """The model to train with: DistributedDataParallel over the group, or the model itself."""
        if self.world == 1:
            return model
        # a one-row batch gives the null token's gradient the strides of a view: harmless, once
        warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
        ids = [device.index] if device.type == "cuda" else None
        return torch.nn.parallel.DistributedDataParallel(model, device_ids=ids)

    def sum(self, x: float, device: torch.device) -> float:
        """x summed over the ranks."""
        if self.world == 1:
            return x
        import torch.distributed as dist

        t = torch.tensor([x], dtype=torch.float64, device=device)
        dist.all_reduce(t)
        return float(t.item())

    def barrier(self) -> None:
        """Wait until every rank gets here (e.g. until rank 0 has written a checkpoint)."""
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier()

    def leave(self) -> None:
        import torch.distributed as dist

        dist.destroy_process_group()
