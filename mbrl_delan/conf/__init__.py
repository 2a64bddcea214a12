"""Where a run is assembled from its config, the one floor that reads configs: the schemas
(`schema`), the registries and plugins (`registry`), the checks (`checks`), the built-in
models and planners (`builders`), a training run (`loop`, `videos`), a fit (`fitting`,
`inverse`) and the bench's names (`bench_names`). The entry points (`train`, `fit`, `bench`)
and every other reader (`runs`, `evaluate`, the benchmarks) build through here."""
