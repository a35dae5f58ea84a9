"""Model weights, apart from the network that uses them (model/): the registry models fetched by
pinned version and SHA-256 (registry.py), the model folder of the paper's models as a contract
(folder.py), and `ga3ce-prep models` (cli.py). Nothing here imports the pipeline; the pipeline
checks its stages' files against this (pipeline/config.py `missing_lines`)."""
