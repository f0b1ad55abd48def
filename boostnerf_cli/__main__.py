"""`python -m boostnerf_cli` is the same CLI as `boostnerf`."""

from boostnerf_cli.cli import main

if __name__ == "__main__":
    main()
