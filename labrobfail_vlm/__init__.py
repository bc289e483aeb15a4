"""LabRobFail-VLM model core. Kept import-light: the simulator imports `labrobfail_vlm.taxonomy` without torch."""
