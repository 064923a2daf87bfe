"""Collectors: expert demonstrations, replay-buffer datasets and evaluation on TorchRL."""
