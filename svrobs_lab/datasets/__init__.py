"""Datasets of measured rollouts: file formats, storage, model export
(docs/datasets.md)."""
