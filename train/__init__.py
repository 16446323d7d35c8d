"""prt.train: from geometry to ground-truth transfer (and, later, fitted networks).

May use torch, trimesh and embreex; install with ``pip install prt-runtime[train]``.
"""
