"""Linear solvers of the reduced normal equations behind one interface (DESIGN sections 5, 5b).

- :mod:`sapgo.solve.band`: the band (recursive partitioning), optimal for long strips;
- :mod:`sapgo.solve.partition`: the partition tree (nested dissection of the station graph);
- :mod:`sapgo.solve.fronts`: dense fronts of the tree, factored, solved and inverted;
- :mod:`sapgo.solve.tree`: the tree solve inside the adjustment (build, factor, precision).
"""
