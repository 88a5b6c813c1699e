"""PilotNet x3: PilotNet convs per frame over 3 frames, then four 4-unit LSTMs; 353 k parameters."""
