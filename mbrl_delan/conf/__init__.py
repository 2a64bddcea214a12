"""Where a run is assembled from its config, the one floor that reads configs: the schemas
(`schema`), the registries and plugins (`registry`), the checks (`checks`), building a
registered model or planner (`builders`), a training run (`loop`, `videos`), a fit
(`fitting`, `inverse`) and the bench's names (`bench_names`). The entry points (`train`,
`fit`, `bench`) and every other reader (`runs`, `evaluate`, the benchmarks) build through
here.

Importing it imports the package's own parts, each of which registers itself beside its
class (`mbrl_delan.registry`): the envs, the world models, the planners and the fit's data
kinds and models."""

import mbrl_delan.data.fit_kinds  # noqa: F401
import mbrl_delan.envs.registry  # noqa: F401
import mbrl_delan.models.delan_config  # noqa: F401
import mbrl_delan.models.delan_ensemble  # noqa: F401
import mbrl_delan.models.ensemble  # noqa: F401
import mbrl_delan.models.inverse_config  # noqa: F401
import mbrl_delan.planners  # noqa: F401
import mbrl_delan.training.whitebox  # noqa: F401
