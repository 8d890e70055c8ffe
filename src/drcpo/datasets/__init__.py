"""Readers (and writers) of public LiDAR data set layouts."""
