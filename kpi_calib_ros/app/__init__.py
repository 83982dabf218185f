"""Application layer: the jobs the CLI and the node both run (identify, diagnose, design,
simulate, demo), composed from the core and the file readers and writers of ``io``."""
