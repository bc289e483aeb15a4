"""Qwen3-VL for LabRobFail: processor without video, local loading, tiny preset, hybrid fine-tuning."""
