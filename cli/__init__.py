"""The ``damcap`` command line: commands only (load, call the pipeline, save)."""
