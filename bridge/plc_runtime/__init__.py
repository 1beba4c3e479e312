"""An executable, cycle-by-cycle model of the project's TwinCAT 3 ST (``plc/``).

(Full description of semantics and the supported subset: see the end of this docstring; filled in below.)
"""

from pmcal.bridge.plc_runtime.builtins import PlcException
from pmcal.bridge.plc_runtime.runtime import PlcFault, PlcRuntime, compile_project

__all__ = ["PlcException", "PlcFault", "PlcRuntime", "compile_project"]
from pmcal.bridge.plc_runtime.comptable_plc import PlcTwin  # noqa: E402

__all__ += ["PlcTwin"]
