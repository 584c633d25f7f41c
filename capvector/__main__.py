"""`python -m capvector …` is the `capvector` command."""

from capvector.flows.cli.main import main

if __name__ == "__main__":
    main()
