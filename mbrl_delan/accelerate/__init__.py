"""The acceleration layer: how the planning rollouts of a world model run fast.

The models and tasks are plain maths; this package alone decides how they run:

- `compile_dynamics`: `torch.compile` with static shapes for the rollouts (`compile.py`);
  `CompiledLoop` for a whole horizon as one compiled loop; `compile_fit` (a `FitGraph`) for
  a fit's loss and its backward pass; `CompiledStep` for code that steps a model itself
  (TorchRL's planners over `ModelEnv`).
- `RolloutThreads`: a batch rolled out in shares on worker threads (`threads.py`).
- `GraphedCalls`: whole rollouts replayed from CUDA graphs (`cuda_graphs.py`).

`ModelObjectiveFactory` (`mbrl_delan/objectives/model.py`) picks among them
from its `compile`, `cuda_graph` and `rollout_threads` settings. The maths in the forms a
compiled rollout runs fastest is in `mbrl_delan.models.kernels`.
"""

from mbrl_delan.accelerate.compile import (
    CompiledLoop,
    CompiledStep,
    FitGraph,
    compile_dynamics,
    compile_fit,
)
from mbrl_delan.accelerate.cuda_graphs import GraphedCalls
from mbrl_delan.accelerate.threads import RolloutThreads

__all__ = [
    "CompiledLoop",
    "CompiledStep",
    "FitGraph",
    "GraphedCalls",
    "RolloutThreads",
    "compile_dynamics",
    "compile_fit",
]
