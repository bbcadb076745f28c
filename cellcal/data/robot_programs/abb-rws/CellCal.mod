MODULE CellCal
    ! cellcal's stop-and-measure loop, commanded through Robot Web Services
    ! (docs/robots.md, ABB). cellcal sets cc_target (degrees) and cc_speed (% of the
    ! axis speeds), then a new cc_seq; this loop moves there with MoveAbsJ ... fine,
    ! waits until the robot is in position and answers cc_ack := that cc_seq. cellcal
    ! then reads the measured joints (rw/motionsystem/mechunits/ROB_1/jointtarget).
    ! Load it into T_ROB1 and run main in AUTO; cellcal refuses manual modes.
    PERS jointtarget cc_target := [[0,0,0,0,30,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];
    PERS num cc_seq := 0;
    PERS num cc_ack := 0;
    PERS num cc_speed := 10;

    PROC main()
        VAR num seq;
        cc_ack := cc_seq;  ! start idle: a request from before the start is not replayed
        WHILE TRUE DO
            WaitUntil cc_seq <> cc_ack;
            seq := cc_seq;  ! the request this move answers
            IF cc_speed < 1 OR cc_speed > 100 cc_speed := 10;
            VelSet cc_speed, 5000;
            MoveAbsJ cc_target, v5000, fine, tool0;  ! fine: an exact stop, never a zone
            WaitRob \InPos;  ! the robot stands in position here
            cc_ack := seq;
        ENDWHILE
    ENDPROC
ENDMODULE
