"""No import cycle in the package (issue #10): the graph of module-level ``import``/``from … import``
statements between accel_bayes modules is acyclic.  A package's ``__init__`` importing its own
submodules is the usual re-export.  The graph and the cycle search are those of
``test_import_graph.py``, which also counts the imports inside functions."""
from test_import_graph import cycles, graph


def test_no_import_cycle():
    g = graph(lazy=False)
    assert "accel_bayes.inference.lm.solver" in g and "accel_bayes.inference.mcmc.kernel" in g
    found = cycles(g)
    assert not found, found
