"""The paper's evaluation on any survey (``seamap evaluate``): Tables I-V and Figs. 3-5.

``inputs`` finds the logs, config, truth and taped quadrats; ``preprocessing`` (Table I),
``registration`` (Table II and each method's time per pair), ``modes`` (the mapping modes
and Tables III-IV), ``blending`` (Table V) compute the tables; ``figures`` draws the
figures; ``report`` writes report.md and tables.json beside the paper's numbers
(``paper``); ``run`` puts them together.
"""
