"""Reports: matrix reports (tables, cells, plots, trajectories), the paper's tables, one episode's report."""
