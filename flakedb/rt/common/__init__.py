"""What every part of the solver shares: the inputs' physical bounds (``params``), the threads independent jobs
run on (``jobs``) and what a series of solves of one recipe family reuses (``reuse``)."""
