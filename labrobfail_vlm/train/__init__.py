"""Training of LabRobFail-VLM: VQA data collation, the hybrid trainer, checkpoints."""
