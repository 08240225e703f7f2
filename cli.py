"""Command line of ssm-ms: ``python cli.py {fit,validate,test,predict} --config configs/<experiment>.yaml``.

LightningCLI in subclass mode with the omegaconf parser: a config names the model and the data by
``class_path`` and may interpolate (``${model.init_args.state_dim}``). ``python cli.py fit --help``
lists every option; ``--print_config`` shows the resolved configuration.
"""

from ssm_ms.cli import main

if __name__ == "__main__":
    main()
