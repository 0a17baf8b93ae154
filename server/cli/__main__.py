from server.cli import main

if __name__ == "__main__":  # worker processes import the main module again: only run it once
    main()
