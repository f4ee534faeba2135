"""One module per pipeline stage. Each module defines NAME, DEPS, VERSION, Params (pydantic), run(inputs, params)
and, when it reads capture files, input_files(capture_dir) -> list of paths whose content keys the cache."""
