"""Reports: the same scene through HBVM and the hosts' own integrators (comparisons, peers),
work-precision diagrams, hard cases, plots and the helpers they share.  They use the adapters
(:mod:`hbvm_md.ase`, :mod:`hbvm_md.rebound`) and the engine; nothing here is
needed to integrate.
"""
