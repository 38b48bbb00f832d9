"""The analytic models (docs/DESIGN.md section 6, the models layer): the solution base and
``RESULTS``, the model registry, the envelope f(t), the matched and undamped ansatz, Coulomb
half-swings and Rizcallah, cubic stiffness, and the error atlas as data the models read.

Imports only the ground modules (``_oscillator``, ``_trig``, ``_cache``)."""
