"""testcell's HTTP service: a thin FastAPI shell over a running :class:`cell.app.cell.Cell`."""
