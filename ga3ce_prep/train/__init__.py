"""Training and evaluating GA3CE over a 3D context store.

Python API (what `ga3ce-prep train/eval/ablate` call):
    from ga3ce_prep.train import TrainConfig, train, evaluate, ablate
    run = train(TrainConfig(store="synth.zarr", out="runs/full", epochs=20))   # -> run folder
    metrics = evaluate("synth.zarr", run / "best.pt", split="test")            # -> EvalResult
    print(format_eval_table(metrics), metrics.methods["model"].mae3d, metrics.to_json())
Other trainers can use `ContextDataset` + `collate` (or `ContextDataset.batch`) directly.
"""
from .ablate import ABLATIONS, ablate, format_ablation_table
from .dataset import Batch, BucketBatchSampler, ContextDataset, collate, store_fingerprint
from .evaluate import evaluate, format_eval_table, predict
from .profiles import DatasetProfile
from .results import EvalResult, GroupMetrics, MethodMetrics
from .trainer import TrainConfig, train

__all__ = ["ABLATIONS", "ablate", "format_ablation_table", "Batch", "BucketBatchSampler",
           "ContextDataset", "collate", "store_fingerprint", "evaluate", "format_eval_table", "predict",
           "DatasetProfile", "EvalResult", "GroupMetrics", "MethodMetrics", "TrainConfig", "train"]
