"""`cadence demo`: the whole closed loop on one machine, no robot and no strap.

Two cells tell it. The lockstep cell (in_lockstep.py, the default) runs every service's own code as a
node of one event loop on data time: a run is a function of its options and seed. The process cell
(processes.py, ``--processes``) runs every service as its own process under a supervisor
(supervise.py), on the wall clock, as systemd would. Both take their options and hand each service its
settings the same way (options.py), watch the same bus (observe.py), show the same live view (view.py),
claim and clean the same run folder (folder.py), and end with the same summary and report (summary.py).
"""
