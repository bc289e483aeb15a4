"""LabRobFail-Bench: parsing of replies, metrics, baselines, reports."""
