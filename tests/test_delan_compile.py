"""The optional compiled planning step gives the eager step's result."""

import pytest
import torch

from mbrl_delan.models.delan import DeLaN
from mbrl_delan.systems.system import load_system


@pytest.mark.slow
def test_compiled_step_equals_eager_step_and_is_dropped_on_dtype_change() -> None:
    system = load_system("acrobot")
    torch.manual_seed(0)
    model = DeLaN(system.layout, system.actuation.float(), system.control_dt, hidden=16)
    model.compile_step = True
    g = torch.Generator().manual_seed(1)
    q, qd, a = (torch.randn(8, k, generator=g) for k in (system.nq, system.nv, system.nu))
    eager = model._step(q, qd, a)
    with torch.inference_mode():
        compiled = model.step(q, qd, a)
    assert model._compiled_step is not None  # the compiled path ran
    torch.testing.assert_close(compiled.q, eager.q, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(compiled.qd, eager.qd, rtol=1e-5, atol=1e-5)
    model.double()  # moving the model drops the compiled step (it is specific to a dtype)
    assert model._compiled_step is None
