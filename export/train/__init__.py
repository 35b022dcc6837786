"""Training of the relighting nets (paper Sec. 3-4): losses, per-net data adapters, the trainer
with resumable checkpoints, and the command line (`python -m export.train NET|all ...`).

See export/train/README.md for the commands, the losses and the decisions behind them.
"""
