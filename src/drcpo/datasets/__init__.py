"""Readers (and writers) of public LiDAR data set layouts."""

__all__: list[str] = []  # the readers and writers are the submodules' own
