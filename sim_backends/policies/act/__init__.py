"""ACT (Zhao et al. 2023, "Action Chunking with Transformers") in plain torch: configuration, model, policy."""
