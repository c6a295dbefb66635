"""Device drivers: one module per protocol family behind one small interface (see ``registry``)."""
