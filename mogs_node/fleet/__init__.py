"""Fleet mapping: many drives in one batch, one Ray task per drive (``mogs batch``).

- :mod:`mogs_node.fleet.drives`: the drive list, run folders, resume (pure);
- :mod:`mogs_node.fleet.task`: one drive's whole node graph through the launcher, on its own bus;
- :mod:`mogs_node.fleet.batch`: the Ray driver (tasks, retries, progress);
- :mod:`mogs_node.fleet.table`: ``fleet.csv``, ``fleet.md`` and the plot across drives.

Ray is an optional extra (``pip install -e '.[fleet]'``), imported only when a batch runs.
docs/fleet.md.
"""
