"""A second simulator of any machine folder (an MJCF and its machine.toml), written separately from pmcal's
generic closed-chain core and importing nothing from pmcal: the corpus's guard against fitting pmcal's own
generator (issue 34). See :mod:`tests.crosssim_chain.machine`.
"""
