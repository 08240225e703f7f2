"""Command line of ssm-ms: ``python cli.py {fit,validate,test,predict} --config configs/<experiment>.yaml``.

The library's command line (``python -m ssm_ms``, ``ssm_ms/__main__.py``) followed by the application's reports
(:mod:`experiments.cli`: a ``test`` run's ``results/<experiment>.md`` beside the ``.json`` it wrote; the console
script ``ssm-ms`` is the same program): LightningCLI in subclass mode with the omegaconf parser: a config names the
model and the data by ``class_path`` and may interpolate (``${model.init_args.state_dim}``). ``python cli.py fit
--help`` lists every option; ``--print_config`` shows the resolved configuration (interpolations resolved after the
command line). A user's mistake prints one ``error: ...`` line and exits non-zero without a traceback;
``SSM_MS_TRACEBACK=1`` shows the full traceback. Ctrl-C prints the command that resumes the run from its last
completed epoch. See ``ssm_ms/cli.py``.
"""

if __name__ == "__main__":
    from experiments.cli import main

    main()
