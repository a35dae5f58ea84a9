"""What the paper's recipe and tables say per dataset, in one place (the trainer, `--n-max auto`,
`--view-noise auto` and the ablation table read it): `DatasetProfile.for_dataset(name)`.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..store import ContextStore


@dataclass(frozen=True)
class DatasetProfile:
    """The per-dataset constants of the paper's recipe; a dataset it does not name (a toy store,
    another dataset) gets the defaults."""

    name: str  # the store's attrs["dataset"]["name"]
    n_max: int = 168  # object slots of the paper's fixed padding N_max (`--n-max auto`); 168 is GFIE's
    view_noise: bool = False  # the paper augments v with noise on this dataset (`--view-noise auto`)
    paper_column: str = "gfie"  # the paper's Tables 4/5 column this dataset's ablations are printed beside

    @classmethod
    def for_dataset(cls, name: str) -> DatasetProfile:
        """The profile of a dataset name (the defaults for a name not in PROFILES)."""
        return PROFILES.get(name, cls(name))

    @classmethod
    def for_store(cls, store: ContextStore) -> DatasetProfile:
        """The profile of the dataset a store was built from."""
        return cls.for_dataset(str(store.attrs.get("dataset", {}).get("name", "")))


PROFILES: dict[str, DatasetProfile] = {p.name: p for p in (
    DatasetProfile("gfie", n_max=168, view_noise=True, paper_column="gfie"),
    DatasetProfile("cad120", n_max=168),
    DatasetProfile("gafa", n_max=278, paper_column="gafa"),
)}
