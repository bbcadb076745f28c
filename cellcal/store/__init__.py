"""The campaign database (SQLite): the one place that holds SQL. Everything else reads and
writes through the named functions of :class:`cellcal.store.database.Store`."""
