"""The simulated PLC: the interpreter of the shipped ST (:mod:`.plc_runtime`) and the strict mock ADS and
Modbus servers that run it (:mod:`.ads_mock`, :mod:`.modbus_mock`, fault plans in :mod:`.faults`). Installed
with the ``sim`` extra (blark, the ST parser); the table contract and the clients (the rest of
:mod:`pmcal.bridge`) never import it."""
