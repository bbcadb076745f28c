from cellcal.cli import main

if __name__ == "__main__":  # not when a spawned process (the camera twin) imports it
    main()
